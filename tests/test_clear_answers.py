"""Settings that used to get a weak answer get a clear one (issue 36, item 5).

``systems.include=[]`` is refused (it named every plant); ``evaluation.variants.range`` must
be a number in (0, 1) (5 drew sign-flipped variants, 0 became 0.25); ``summary.json`` says
which policy it describes, the same way each time; an Optuna study name must be a plain name
(``../x`` wrote its trials outside the project).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict
from generalist_control.data.generation import variants_config
from generalist_control.evaluate import run as evaluate_run
from generalist_control.evaluation.eval_config import read_evaluation
from generalist_control.generate import run as generate_run
from generalist_control.model.policy import save_policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.definition import PlantConfigError
from generalist_control.plants.variants import DEFAULT_RANGE, variant_range
from generalist_control.simulation.lqi import LQIGains, design_lqi
from generalist_control.tune import run as study_run
from helpers import compose_cfg, lqi_law_policy

# --- systems.include=[] ------------------------------------------------------------------


def test_an_empty_include_list_names_no_plant_and_is_refused(tmp_path):
    cfg = compose_cfg("systems.include=[]", f"paths.data_dir={tmp_path / 'demos'}")
    with pytest.raises(PlantConfigError, match=r"systems\.include=\[\] names no plant.*drop"):
        plants_from_config(as_dict(cfg.systems))
    with pytest.raises(PlantConfigError, match=r"name plants, e\.g\. systems\.include=\[cstr\]"):
        generate_run(cfg)
    assert list(tmp_path.iterdir()) == []  # refused before anything was written
    everything = plants_from_config(
        as_dict(compose_cfg().systems)
    )  # the key left out: every plant
    assert len(everything) == len(compose_cfg().systems.plants) >= 25


# --- evaluation.variants.range -----------------------------------------------------------


@pytest.mark.parametrize("value", [5, 1.0, 0, 0.0, -0.1, "wide", True])
def test_a_variant_range_outside_zero_one_is_refused_naming_the_key(value):
    node = as_dict(compose_cfg().evaluation)
    node["variants"]["range"] = value
    with pytest.raises(ValueError, match=r"evaluation\.variants\.range must (be a number|lie in)"):
        read_evaluation(node)
    with pytest.raises(ValueError, match=r"data\.variants\.range = .* in \(0, 1\)"):
        variants_config({"variants": {**_VARIANTS, "range": value}})


#: A data.variants block as conf/data/demos.yaml writes one, switched on.
_VARIANTS = {"enabled": True, "count": 8, "seed": 1013, "max_tries": 10, "range": 0.25}


def test_a_range_left_out_is_the_default_and_a_valid_one_is_kept():
    assert variant_range(None, "evaluation.variants.range") == DEFAULT_RANGE == 0.25
    assert variant_range(0.4, "evaluation.variants.range") == 0.4
    assert variants_config({"variants": {**_VARIANTS, "range": 0.1}})["range"] == 0.1
    with pytest.raises(ValueError, match=r"data.variants needs \['count'\]"):
        variants_config({"variants": {k: v for k, v in _VARIANTS.items() if k != "count"}})


# --- summary.json names its policy ---------------------------------------------------------


def _half(plant) -> LQIGains:
    g = design_lqi(plant)
    return LQIGains(Kx=g.Kx / 2, Ki=g.Ki / 2, P=g.P, poles=g.poles)


def _evaluate(policy: Path, reports: Path, tmp_path: Path, uri: str) -> dict:
    overrides = [
        f"policy={policy}",
        "systems.include=[cstr]",
        f"paths.reports_dir={reports}",
        "~evaluation.scenarios",
        "+evaluation.scenarios={step: {kind: step, amplitude: 1.0, duration: 3.0}}",
        "evaluation.setpoint=null",
        "evaluation.plots=false",
        "evaluation.backend=torch",
        f"logger.tracking_uri={uri}",
        f"logger.experiment_name={tmp_path.name}",
    ]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        evaluate_run(compose("config", overrides=overrides))
    return json.loads((reports / "summary.json").read_text())


def test_summary_json_is_the_same_for_the_same_weights_and_says_which_policy(tmp_path, mlflow_uri):
    """What reproduces is in summary.json (committed); run ids, date, machine are not."""
    policy = tmp_path / "models" / "policy.ckpt"
    reports = tmp_path / "reports"
    full, meta = lqi_law_policy(["cstr"], design_lqi)
    summaries, records = [], []
    for data_dir in ("/here/demos", "/there/demos"):
        save_policy(policy, full, {**meta, "data_dir": data_dir})
        _evaluate(policy, reports, tmp_path, mlflow_uri)
        summaries.append((reports / "summary.json").read_bytes())
        records.append(json.loads((reports / "provenance.json").read_text()))
    assert summaries[0] == summaries[1]  # other file bytes, the same weights
    assert [r["policy"]["mlflow_run_id"] for r in records] == [None, None]  # no run wrote it
    assert records[0]["mlflow"]["run_id"] != records[1]["mlflow"]["run_id"]
    assert {"date", "machine", "command"} <= set(records[0])
    summary = json.loads(summaries[0])
    assert set(summary["policy"]) == {"source", "weights_sha256"}
    assert summary["policy"]["source"] == str(policy)
    assert set(summary["provenance"]) == {"command"}
    half, meta = lqi_law_policy(["cstr"], _half)
    save_policy(policy, half, {**meta, "data_dir": "/here/demos"})
    other = _evaluate(policy, reports, tmp_path, mlflow_uri)
    assert other["policy"]["weights_sha256"] != summary["policy"]["weights_sha256"]
    assert {"diverged", "ratios", "tracking", "anti_windup", "quality_bar"} <= set(other)


# --- hparams_search.study_name -------------------------------------------------------------


@pytest.mark.parametrize("name", ["../escape", "a/b", "..", ".hidden", "a\\b", "", "x'y"])
def test_a_study_name_that_is_not_a_plain_name_is_refused(tmp_path, name):
    db = tmp_path / "optuna.db"
    overrides = [
        f"hparams_search.storage=sqlite:///{db}",
        f"hparams_search.trials_dir={tmp_path / 'trials'}",
        "hparams_search.n_trials=0",
    ]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("tune", overrides=overrides)
    cfg.hparams_search.study_name = name  # as a config file may hold it
    with pytest.raises(ValueError, match=r"study_name = .* is not a plain name.*e\.g\."):
        study_run(cfg)
    assert list(tmp_path.iterdir()) == []  # refused before the storage was opened
