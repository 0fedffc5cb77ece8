"""Nothing of the user's is deleted, nothing is left half-written, data are verified at load.

Issue 10, items 1 and 3: output folders are replaced only when they hold nothing but the
stage's own outputs; a kill between the two renames of a publish never loses the dataset;
a changed dataset is refused at load with the command that regenerates it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from generalist_control.common import atomic
from generalist_control.common.atomic import ForeignDirectoryError
from generalist_control.common.sections import as_dict
from generalist_control.data.demos import (
    CorruptDataError,
    DemoSet,
    content_hash,
    load_demos,
    manifest_digest,
    write_demos,
)
from generalist_control.evaluate import run as evaluate_run
from generalist_control.evaluation.eval_config import read_evaluation
from generalist_control.evaluation.runner import Evaluation
from generalist_control.evaluation.writer import write_reports
from generalist_control.generate import run as generate_run
from generalist_control.reports.ablation import Inputs, write_report
from generalist_control.reports.report_settings import Tolerance
from helpers import compose_cfg

REPO = Path(__file__).resolve().parents[1]
TINY = ("systems=paper", "systems.include=[cstr]", "data.duration=1.0")

#: The report's inputs with nothing but the rules (conf/report, conf/evaluation).
NO_INPUTS = Inputs(Tolerance(2.0, 0.01, 0.10), {"ISE_ratio": 1.05, "RMSE_ratio": 1.1})


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in path.rglob("*") if p.is_file()}


def _user_folder(path: Path) -> dict[str, bytes]:
    path.mkdir(parents=True, exist_ok=True)
    (path / "notes.txt").write_text("my own notes")
    (path / ".gitkeep").write_text("")
    return _tree(path)


def test_generate_refuses_a_folder_of_user_files_and_touches_nothing(tmp_path):
    before = _user_folder(tmp_path / "mine")
    cfg = compose_cfg(*TINY, f"paths.data_dir={tmp_path / 'mine'}")
    with pytest.raises(ForeignDirectoryError, match=r"notes\.txt.*Nothing was changed"):
        generate_run(cfg)
    assert _tree(tmp_path / "mine") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]  # no staging left


def test_generate_refuses_the_data_folder_itself(tmp_path):
    """The issue's case: ``paths.data_dir=data`` (a folder with .gitignore) is refused."""
    data = tmp_path / "data"
    data.mkdir()
    (data / ".gitignore").write_text("/demos\n")
    cfg = compose_cfg(*TINY, f"paths.data_dir={data}")
    with pytest.raises(ForeignDirectoryError, match=r"paths\.data_dir.*\.gitignore"):
        generate_run(cfg)
    assert (data / ".gitignore").read_text() == "/demos\n"


def test_a_previous_dataset_is_replaced(tmp_path):
    out = tmp_path / "demos"
    first = generate_run(compose_cfg(*TINY, f"paths.data_dir={out}"))
    second = generate_run(compose_cfg(*TINY, "data.duration=1.5", f"paths.data_dir={out}"))
    assert first["content_hash"] != second["content_hash"]
    assert (
        json.loads((out / "manifest.json").read_text())["content_hash"] == second["content_hash"]
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]


def test_evaluate_refuses_a_reports_folder_of_user_files(tmp_path):
    before = _user_folder(tmp_path / "reports")
    cfg = compose_cfg(f"paths.reports_dir={tmp_path / 'reports'}", "policy=/no/such/policy.ckpt")
    with pytest.raises(ForeignDirectoryError, match=r"paths\.reports_dir"):
        evaluate_run(cfg)  # refused before the (missing) policy is even looked for
    assert _tree(tmp_path / "reports") == before
    import pandas as pd

    bar = read_evaluation(as_dict(cfg.evaluation)).quality_bar
    nothing = Evaluation(pd.DataFrame(), {})
    with pytest.raises(ForeignDirectoryError):
        write_reports(nothing, tmp_path / "reports", bar, {}, plots=False)
    assert _tree(tmp_path / "reports") == before


def test_report_refuses_a_folder_of_user_files(tmp_path):
    before = _user_folder(tmp_path / "ablation")
    with pytest.raises(ForeignDirectoryError, match=r"report\.out_dir"):
        write_report(tmp_path / "ablation", {"hidden": {}, "experts": {}}, [], NO_INPUTS)
    assert _tree(tmp_path / "ablation") == before


def test_a_file_inside_an_owned_subfolder_is_foreign(tmp_path):
    out, owned = tmp_path / "eval", {"summary.json": None, "plots": "*.png"}
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "a.png").write_bytes(b"png")
    (out / "summary.json").write_text("{}")
    atomic.check_replaceable(out, owned)  # only outputs (a folder from before markers): fine
    (out / "plots" / "keep.txt").write_text("mine")
    with pytest.raises(ForeignDirectoryError, match=r"plots/keep\.txt"):
        atomic.check_replaceable(out, owned)


_KILL = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from generalist_control.common import atomic
    from generalist_control.data.demos import load_demos, write_demos

    src, out, mode = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    demos, manifest = load_demos(src)
    manifest = {**manifest, "note": "second"}
    real_replace, real_rmtree = os.replace, atomic.shutil.rmtree
    if mode == "two-renames":
        atomic._exchange = lambda a, b: False  # a system without renameat2

        def replace(a, b):
            real_replace(a, b)
            if ".old-" in str(b):  # killed between the two renames
                os.kill(os.getpid(), signal.SIGKILL)

        atomic.os.replace = replace
    else:
        def rmtree(path, *args, **kwargs):  # killed after the swap, before the clean-up
            os.kill(os.getpid(), signal.SIGKILL)

        atomic.shutil.rmtree = rmtree
    write_demos(out, demos, manifest)
    """
)


@pytest.mark.parametrize("mode", ["two-renames", "exchange"])
def test_a_kill_during_publish_never_loses_the_dataset(tmp_path, tiny_data_dir, mode):
    out = tmp_path / "demos"
    demos, manifest = load_demos(tiny_data_dir)
    write_demos(out, demos, manifest)
    before = _tree(out)
    proc = subprocess.run([sys.executable, "-c", _KILL, str(tiny_data_dir), str(out), mode])
    assert proc.returncode == -9
    if mode == "two-renames":
        assert not out.exists()  # the old dataset sits under .demos.old-<pid>-0 ...
        left = sorted(p.name.split("-")[0] for p in tmp_path.iterdir())
        assert left == [".demos.old", ".demos.tmp"]  # old outputs, unfinished new ones
        again, _ = load_demos(out)  # ... and the next reader puts it back
        assert _tree(out) == before
        assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]
    else:
        assert any(p.name.startswith(".demos.tmp-") for p in tmp_path.iterdir())
        again, m = load_demos(out)  # the new dataset is complete and in place
        assert m["note"] == "second"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]  # leftover cleaned
    np.testing.assert_array_equal(again.u, demos.u)
    for leftover in ("data/.demos.tmp-123-abc", "data/.demos.old-123-0"):
        ignored = subprocess.run(["git", "check-ignore", "-q", leftover], cwd=REPO)
        assert ignored.returncode == 0, f"{leftover} must be ignored by git"


def _copy(tiny_data_dir: Path, tmp_path: Path) -> Path:
    out = tmp_path / "demos"
    out.mkdir()
    for p in tiny_data_dir.iterdir():
        (out / p.name).write_bytes(p.read_bytes())
    return out


def _resealed(manifest: dict) -> dict:
    """A manifest changed by someone who also recomputed its digest (test_manifest_digest.py
    shows that a changed manifest is refused otherwise): the checks below still hold."""
    return {**manifest, "manifest_digest": manifest_digest(manifest)}


def test_a_sign_flipped_control_column_is_refused(tmp_path, tiny_data_dir):
    out = _copy(tiny_data_dir, tmp_path)
    tbl = pq.read_table(out / "trajectories.parquet")
    u = tbl.column("u").to_numpy()
    tbl = tbl.set_column(tbl.schema.get_field_index("u"), "u", [-u])
    pq.write_table(tbl, out / "trajectories.parquet", compression="zstd")
    with pytest.raises(CorruptDataError, match=r"trajectories\.parquet.*python -m generalist"):
        load_demos(out)


def test_a_tampered_file_with_a_matching_file_digest_fails_the_content_hash(
    tmp_path, tiny_data_dir
):
    """Even with the manifest's file digest updated, the arrays' hash gives it away."""
    import hashlib

    out = _copy(tiny_data_dir, tmp_path)
    tbl = pq.read_table(out / "trajectories.parquet")
    u = tbl.column("u").to_numpy()
    tbl = tbl.set_column(tbl.schema.get_field_index("u"), "u", [-u])
    pq.write_table(tbl, out / "trajectories.parquet", compression="zstd")
    manifest = json.loads((out / "manifest.json").read_text())
    digest = hashlib.sha256((out / "trajectories.parquet").read_bytes()).hexdigest()
    manifest["files"]["trajectories.parquet"] = "sha256:" + digest
    (out / "manifest.json").write_text(json.dumps(_resealed(manifest)))
    with pytest.raises(CorruptDataError, match=r"content hash sha256:\w+, the manifest says"):
        load_demos(out)


def test_a_wrong_trajectory_count_is_refused(tmp_path, tiny_data_dir):
    out = _copy(tiny_data_dir, tmp_path)
    manifest = json.loads((out / "manifest.json").read_text())
    B, N = manifest["n_trajectories"], manifest["steps_per_trajectory"]
    manifest["n_trajectories"], manifest["steps_per_trajectory"] = B // 2, N * 2  # same rows
    (out / "manifest.json").write_text(json.dumps(_resealed(manifest)))
    with pytest.raises(CorruptDataError, match=r"not whole trajectories"):
        load_demos(out)
    manifest["n_trajectories"], manifest["steps_per_trajectory"] = B - 1, N
    (out / "manifest.json").write_text(json.dumps(_resealed(manifest)))
    with pytest.raises(CorruptDataError, match=rf"{B * N} rows, not {B - 1} trajectories"):
        load_demos(out)


def test_the_loaded_hash_is_the_one_computed_from_the_arrays(tiny_data_dir):
    demos, manifest = load_demos(tiny_data_dir)
    assert isinstance(demos, DemoSet)
    assert manifest["content_hash"] == content_hash(demos, manifest["config"])
