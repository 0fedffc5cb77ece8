"""The evaluation's figures: fewer, and drawn in forked processes beside the evaluation."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from generalist_control.evaluation import background
from generalist_control.evaluation.background import FigureJob, figures_beside
from generalist_control.evaluation.plots import PER_PLANT, plot_all, plotted
from generalist_control.simulation.simulate import Trajectory


@pytest.fixture(autouse=True)
def _no_folder_left(tmp_path, monkeypatch):
    """Every job's folder (made in the temporary directory) is gone after each test."""
    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    yield
    assert not list(temp.iterdir())


def _tr(seed: int, rows: int = 1, n: int = 40) -> Trajectory:
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.normal(size=(rows, n + 1)), axis=1)
    return Trajectory(
        t=np.arange(n + 1) * 0.05, x=y[..., None], u=rng.normal(size=(rows, n)),
        r=np.ones((rows, n)), y=y, diverged=np.zeros(rows, bool),
    )  # fmt: skip


def _trajs() -> dict:
    systems = [f"plant{i}" for i in range(PER_PLANT + 2)]
    return {
        "step": {c: {s: _tr(i) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
        "sine": {c: {s: _tr(i + 9) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
        "limits": {c: {"plant0": _tr(3)} for c in ("GC", "GC-AW", "LQI", "LQI-AW")},
        "family": {c: {s: _tr(i, rows=2) for i, s in enumerate(systems)} for c in ("GC", "LQI")},
    }


@pytest.mark.parametrize("forked", [True, False])
def test_figures_drawn_beside_are_the_figures_drawn_here(tmp_path, forked):
    here = plot_all(_trajs(), tmp_path / "here")
    job = FigureJob(forked=forked)  # made before the trajectories exist, as the stage does
    try:
        job.draw(_trajs())
        beside = job.collect(tmp_path / "beside")
    finally:
        job.close()
    assert sorted(p.name for p in beside) == sorted(p.name for p in here)
    for path in here:  # the same files, byte for byte
        assert (tmp_path / "beside" / path.name).read_bytes() == path.read_bytes(), path.name
    names = {p.name for p in here}
    assert "plant0_step_sine.png" in names and "plant0_limits.png" in names
    assert "family.png" in names and "plant0_family.png" not in names  # many plants: one grid
    assert not job.dir.exists()


def test_what_is_sent_to_the_drawing_process_draws_the_same_figures(tmp_path):
    trajs = _trajs() | {"ramp": _trajs()["step"]}  # a scenario no figure shows
    sent = plotted(trajs)
    assert "ramp" not in sent and set(sent["limits"]) == {"GC", "GC-AW", "LQI", "LQI-AW"}
    assert all(tr.x.size == 0 and tr.y.shape[0] == 1 for tr in sent["family"]["GC"].values())
    full, small = plot_all(trajs, tmp_path / "full"), plot_all(sent, tmp_path / "small")
    assert [p.name for p in small] == [p.name for p in full]
    for a, b in zip(full, small, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_a_job_never_given_trajectories_ends_and_leaves_nothing():
    job = FigureJob()
    assert job.proc is not None and job.proc.is_alive()
    job.close()
    assert job.proc.exitcode is not None and not job.dir.exists()
    for forked in (True, False):
        job = FigureJob(forked=forked)
        with pytest.raises(RuntimeError, match="before FigureJob.draw"):
            job.collect("unused")
        job.close()


def test_a_failed_drawing_is_an_error_not_a_missing_figure(tmp_path):
    good = _tr(3)
    bad = Trajectory(t=good.t[:5], x=good.x, u=good.u, r=good.r, y=good.y, diverged=good.diverged)
    broken = {"limits": {"GC": {"plant0": bad}}}  # times and samples that do not match
    with figures_beside() as job, pytest.raises(RuntimeError, match="figures failed"):
        assert job is not None
        job.draw(broken)
        job.collect(tmp_path / "plots")


def test_the_early_job_is_taken_over_or_closed(monkeypatch):
    monkeypatch.setattr(background, "_early", None)
    background.start_early()
    early = background._early
    assert early is not None
    with figures_beside() as job:
        assert job is early and background._early is None
    assert not early.dir.exists()
    background.start_early()
    early = background._early
    with figures_beside(enabled=False) as job:
        assert job is None
    assert not early.dir.exists() and early.proc is not None and not early.proc.is_alive()


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in path.read_text().split()] if path.exists() else []


@pytest.mark.skipif(
    not Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists(),
    reason="needs Linux's /proc/<pid>/task/<tid>/children",
)
def test_closing_a_job_while_it_draws_stops_every_drawer(tmp_path, capfd):
    many = [f"plant{i}" for i in range(60)]  # seconds of drawing
    trajs = {"step": {c: {s: _tr(i) for i, s in enumerate(many)} for c in ("GC", "LQI")}}
    job = FigureJob()
    assert job.proc is not None and job.proc.pid is not None
    job.draw(trajs)
    deadline = time.monotonic() + 60
    while not (drawers := _children(job.proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert drawers, "the drawing process forked no second drawer"
    job.close()
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{pid}").exists() for pid in drawers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{pid}").exists() for pid in drawers)
    assert not job.dir.exists()
    # stopped, not left to fail on the folder that close() removed
    assert "Traceback" not in capfd.readouterr().err


def test_an_early_job_whose_process_died_is_replaced_and_its_folder_removed(monkeypatch):
    monkeypatch.setattr(background, "_early", None)
    background.start_early()
    dead = background._early
    assert dead is not None and dead.proc is not None
    dead.proc.kill()
    dead.proc.join()
    with figures_beside() as job:
        assert job is not None and job is not dead and job.proc is not None
        assert job.proc.is_alive() and not dead.dir.exists()
