"""MLflow's comparison of an ablation: the children of one parent, d, M and scores side by side.

The fake ablation of ``scripts/check_mlflow_compare.py`` (the script that checks the
Compare page in headless Chromium) is read back through what the UI reads, MLflow's REST
API of a real ``mlflow server`` on 127.0.0.1, and through ``mlflow.search_runs``, the table
docs/sweeps.md shows.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import mlflow
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "check_mlflow_compare.py"
_spec = importlib.util.spec_from_file_location("check_mlflow_compare", SCRIPT)
assert _spec is not None and _spec.loader is not None
compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare)


def test_search_runs_puts_the_childrens_params_and_scores_side_by_side(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    exp_id, parent_id, ids = compare.fake_store(uri, tmp_path / "artifacts")
    mlflow.set_tracking_uri(uri)
    table = mlflow.search_runs(
        experiment_ids=[exp_id], filter_string=f"tags.mlflow.parentRunId = '{parent_id}'"
    ).set_index("tags.mlflow.runName")
    assert set(table.index) == set(compare.POINTS)
    for name, (d, m, seed, n_par, mse, passed) in compare.POINTS.items():
        row = table.loc[name]
        assert (row["params.model.hidden"], row["params.experts"]) == (str(d), str(m))
        assert row["params.n_parameters"] == str(n_par) and row["params.seed"] == str(seed)
        assert row["metrics.closed_loop/mse/crazyflie_altitude"] == pytest.approx(mse)
        assert row["metrics.eval/bar_passed"] == passed


@pytest.mark.slow
def test_the_rest_api_of_a_server_gives_the_compare_view_its_columns(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    exp_id, parent_id, ids = compare.fake_store(uri, tmp_path / "artifacts")
    port = compare.free_port()
    with compare.mlflow_server(uri, tmp_path / "artifacts", port, tmp_path / "log") as base:
        runs = compare.search_children(base, exp_id, parent_id)
        url = compare.compare_url(base, exp_id, list(ids.values()))
    assert {r["info"]["run_id"] for r in runs} == set(ids.values())
    for run in runs:
        params = {p["key"]: p["value"] for p in run["data"]["params"]}
        metrics = {m["key"]: m["value"] for m in run["data"]["metrics"]}
        d, m, _, n_par, mse, _ = compare.POINTS[run["info"]["run_name"]]
        assert params["model.hidden"] == str(d) and params["experts"] == str(m)
        assert params["n_parameters"] == str(n_par)
        assert metrics["closed_loop/mse/crazyflie_altitude"] == pytest.approx(mse)
        assert metrics["eval/bar/stable_everywhere"] == 1.0
    assert url.startswith(f"http://127.0.0.1:{port}/#/compare-runs?runs=")
    assert all(i in url for i in ids.values())
    assert compare.check("".join(f">{d}<" for d, *_ in compare.POINTS.values())) != []
