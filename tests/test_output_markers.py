"""A stage replaces or deletes only what it recorded writing (issue 36, items 1 and 2).

Every published folder holds a marker (``.gc-outputs.json``) listing what the stage wrote;
a folder may be replaced only if its marker lists every entry, and a folder named like an
interrupted publish's leftover (``.demos.old-<pid>``) is one only if it carries the marker.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from generalist_control.common import atomic
from generalist_control.common.atomic import MARKER, ForeignDirectoryError
from generalist_control.data.demos import MissingDataError, load_demos, write_demos
from generalist_control.evaluation import writer
from generalist_control.reports.ablation import Inputs, write_report
from generalist_control.reports.report_settings import Tolerance

REPO = Path(__file__).resolve().parents[1]
EMPTY_SWEEPS = {"hidden": {}, "experts": {}}

#: The report's inputs with nothing but the rules (conf/report, conf/evaluation).
NO_INPUTS = Inputs(Tolerance(2.0, 0.01, 0.10), {"ISE_ratio": 1.05, "RMSE_ratio": 1.1})


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in path.rglob("*") if p.is_file()}


def _dead_pid() -> int:
    """The pid of a process that has exited."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _user_pictures(out: Path) -> dict[str, bytes]:
    out.mkdir(parents=True)
    (out / "holiday.png").write_bytes(b"\x89PNG my holiday")
    (out / "budget.csv").write_text("month,spent\njan,3\n")
    return _tree(out)


# --- item 1: the stage's own output is what its marker lists --------------------------------


def test_a_folder_of_the_users_pictures_and_tables_is_not_replaced_by_the_report(tmp_path):
    """The issue's case: ``report.out_dir`` at a folder of the user's *.png and *.csv."""
    out = tmp_path / "ablation"
    before = _user_pictures(out)
    with pytest.raises(ForeignDirectoryError, match=r"report\.out_dir.*budget\.csv, holiday"):
        write_report(out, EMPTY_SWEEPS, [], NO_INPUTS)
    assert _tree(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["ablation"]  # no staging folder left


def test_the_marker_lists_what_was_written_and_only_that_is_replaced(tmp_path):
    out = tmp_path / "ablation"
    write_report(out, EMPTY_SWEEPS, [], NO_INPUTS)
    marker = json.loads((out / MARKER).read_text())
    on_disk = sorted(p.name for p in out.iterdir() if p.name != MARKER)
    assert marker["entries"] == on_disk and "summary.json" in on_disk
    assert marker["setting"] == "report.out_dir"
    write_report(out, EMPTY_SWEEPS, [], NO_INPUTS)  # its own folder: replaced
    (out / "holiday.png").write_bytes(b"\x89PNG mine")  # a user's picture among the outputs
    with pytest.raises(ForeignDirectoryError, match=r"\(holiday\.png;"):
        write_report(out, EMPTY_SWEEPS, [], NO_INPUTS)
    assert (out / "holiday.png").read_bytes() == b"\x89PNG mine"


def _publish(out: Path, files: dict[str, bytes]) -> None:
    with atomic.staging_directory(out) as staging:
        for name, data in files.items():
            (staging / name).parent.mkdir(parents=True, exist_ok=True)
            (staging / name).write_bytes(data)
        atomic.publish_directory(staging, out, writer.OWNED, "paths.reports_dir")


def test_sub_folders_are_listed_file_by_file(tmp_path):
    out = tmp_path / "eval"
    _publish(out, {"summary.json": b"{}", "plots/a.png": b"png"})
    assert json.loads((out / MARKER).read_text())["entries"] == [
        "plots/",
        "plots/a.png",
        "summary.json",
    ]
    _publish(out, {"summary.json": b"{}", "plots/b.png": b"png"})  # replaced: only b now
    assert sorted(_tree(out)) == [MARKER, "plots/b.png", "summary.json"]
    (out / "plots" / "mine.png").write_bytes(b"mine")
    (out / "extra").mkdir()  # an empty folder of the user's is foreign too
    with pytest.raises(ForeignDirectoryError, match=r"extra, plots/mine\.png"):
        atomic.check_replaceable(out, writer.OWNED)


def test_a_marker_that_is_not_the_projects_makes_the_folder_foreign(tmp_path):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    (out / MARKER).write_text("not json")
    with pytest.raises(ForeignDirectoryError, match=r"not a record this project wrote"):
        atomic.check_replaceable(out, writer.OWNED)


def test_a_folder_from_before_markers_is_accepted_only_with_the_exact_names(tmp_path):
    """No marker: the stage's exact names only; a pattern never counts on its own."""
    out = tmp_path / "eval"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "cstr_step.png").write_bytes(b"png")
    with pytest.raises(ForeignDirectoryError, match=r"plots/cstr_step\.png"):
        atomic.check_replaceable(out, writer.OWNED)  # PNGs alone: could be anyone's
    (out / "summary.json").write_text("{}")
    atomic.check_replaceable(out, writer.OWNED)  # beside the stage's summary: its plots
    _publish(out, {"summary.json": b"{}"})  # replaced, and now marked
    assert json.loads((out / MARKER).read_text())["entries"] == ["summary.json"]
    with pytest.raises(ValueError, match=r"exact names, not patterns"):
        atomic.check_replaceable(out.with_name("other"), {"*.png": None})


def test_every_publisher_marks_its_folder(tiny_data_dir):
    """The dataset too: its marker lists the manifest and the trajectories; git ignores it."""
    marker = json.loads((tiny_data_dir / MARKER).read_text())
    assert marker["entries"] == ["manifest.json", "trajectories.parquet"]
    assert marker["setting"] == "paths.data_dir"
    for path in ("data/demos/.gc-outputs.json", "reports/variants/.gc-outputs.json"):
        ignored = subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO)
        assert ignored.returncode == 0, f"{path} must be ignored by git"


# --- item 2: leftovers are recognised by the marker, never by name ---------------------------


def test_a_users_folder_named_like_a_leftover_is_never_moved(tmp_path):
    """The issue's case: ``.demos.old-<pid>`` with the user's notes and no ``demos``."""
    mine = tmp_path / f".demos.old-{_dead_pid()}"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes")
    with pytest.raises(MissingDataError, match=r"manifest\.json is missing"):
        load_demos(tmp_path / "demos")
    assert not (tmp_path / "demos").exists()
    assert _tree(mine) == {"notes.txt": b"my notes"}


def test_users_folders_named_like_leftovers_survive_a_publish(tmp_path, tiny_data_dir):
    pid = _dead_pid()
    mine = [tmp_path / f".demos.old-{pid}", tmp_path / f".demos.tmp-{pid}-abc"]
    for folder in mine:
        folder.mkdir()
        (folder / "notes.txt").write_text("mine")
    demos, manifest = load_demos(tiny_data_dir)
    write_demos(tmp_path / "demos", demos, manifest)
    write_demos(tmp_path / "demos", demos, manifest)  # a replace: recover() runs first
    load_demos(tmp_path / "demos")
    for folder in mine:
        assert _tree(folder) == {"notes.txt": b"mine"}


_KILLED_MID_WORK = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from generalist_control.common import atomic

    with atomic.staging_directory(Path(sys.argv[1])) as staging:
        (staging / "half.csv").write_text("a,b\\n")  # the stage's work, not yet listed
        os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_a_staging_folder_of_a_killed_stage_is_still_cleaned_up(tmp_path):
    out = tmp_path / "eval"
    proc = subprocess.run([sys.executable, "-c", _KILLED_MID_WORK, str(out)])
    assert proc.returncode == -signal.SIGKILL
    (left,) = tmp_path.iterdir()
    assert left.name.startswith(".eval.tmp-") and (left / "half.csv").is_file()
    atomic.recover(out)
    assert list(tmp_path.iterdir()) == []
