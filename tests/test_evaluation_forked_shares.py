"""Work shared with forked children: shares, results back in order, errors, and children
that never outlive their parent nor hold a pipe end they do not use."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from generalist_control.evaluation import forked_shares
from generalist_control.evaluation.forked_shares import balanced, can_fork, fork_map
from generalist_control.evaluation.runner import run_suite
from generalist_control.plants.catalog import load_plant
from test_evaluate import PLANTS, SCENARIOS, LQIRuntime

needs_fork = pytest.mark.skipif(not can_fork(), reason="the system cannot fork")


def test_balanced_shares_the_cost_largest_first():
    assert balanced([3, 1, 1, 1], 2) == [[0], [1, 2, 3]]
    assert balanced([1, 1, 1, 1], 2) == [[0, 2], [1, 3]]
    groups = balanced([5.0, 4.0, 3.0, 3.0, 2.0, 1.0], 2)
    costs = [sum([5.0, 4.0, 3.0, 3.0, 2.0, 1.0][i] for i in g) for g in groups]
    assert sorted(i for g in groups for i in g) == list(range(6)) and costs == [9.0, 9.0]
    assert balanced([1.0], 3) == [[0]]  # no empty share
    with pytest.raises(ValueError, match="parts must be at least 1"):
        balanced([1.0], 0)


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


@needs_fork
def test_fork_map_runs_the_other_items_in_children_and_keeps_the_order():
    out = fork_map(_pid_and_square, [1, 2, 3])
    assert [sq for _, sq in out] == [1, 4, 9]
    pids = [pid for pid, _ in out]
    assert pids[0] == os.getpid() and len(set(pids)) == 3


def test_fork_map_runs_everything_here_where_nothing_forks(monkeypatch):
    monkeypatch.setattr(forked_shares, "can_fork", lambda: False)
    out = fork_map(_pid_and_square, [1, 2, 3])
    assert out == [(os.getpid(), 1), (os.getpid(), 4), (os.getpid(), 9)]


def _fail_in_child(x: int) -> int:
    if x == 2:
        raise KeyError(f"no plant {x}")
    return x


@needs_fork
def test_an_error_in_a_child_is_raised_here_with_its_traceback():
    with pytest.raises(KeyError, match="no plant 2") as info:
        fork_map(_fail_in_child, [1, 2])
    assert any("in the forked share" in note and "_fail_in_child" in note
               for note in info.value.__notes__)  # fmt: skip


class _Unpicklable(Exception):
    def __init__(self, a: int, b: int) -> None:  # pickling rebuilds it with one argument
        super().__init__(f"{a} and {b}")


def _raise_unpicklable(x: int) -> int:
    if x:
        raise _Unpicklable(1, 2)
    return x


def _die(x: int) -> int:
    if x:
        os._exit(3)
    return x


@needs_fork
def test_a_child_that_cannot_send_its_error_or_dies_is_an_error_here():
    with pytest.raises(RuntimeError, match="_Unpicklable: 1 and 2"):
        fork_map(_raise_unpicklable, [0, 1])
    with pytest.raises(RuntimeError, match=r"ended without a result \(exit code 3\)"):
        fork_map(_die, [0, 1])


@needs_fork
def test_the_suite_in_two_processes_equals_one_and_logs_every_scenario(caplog):
    plants = [load_plant(n) for n in PLANTS]
    scenarios = {name: {**spec, "duration": 3.0} for name, spec in SCENARIOS.items()}
    one = run_suite(LQIRuntime(PLANTS), plants, scenarios, processes=1)
    with caplog.at_level(logging.INFO, logger="generalist_control.evaluation.loop_layout"):
        two = run_suite(LQIRuntime(PLANTS), plants, scenarios, processes=2)
    pd.testing.assert_frame_equal(one.metrics, two.metrics, check_exact=True)
    assert list(one.trajectories) == list(two.trajectories) == list(scenarios)
    for scen, by_ctrl in one.trajectories.items():
        assert list(by_ctrl) == list(two.trajectories[scen])
        for ctrl, by_plant in by_ctrl.items():
            assert list(by_plant) == list(two.trajectories[scen][ctrl])
            for name, tr in by_plant.items():
                np.testing.assert_array_equal(tr.x, two.trajectories[scen][ctrl][name].x)
                np.testing.assert_array_equal(tr.u, two.trajectories[scen][ctrl][name].u)
    lines = [r.getMessage() for r in caplog.records if r.name.endswith("evaluation.loop_layout")]
    assert [line.split(":")[0] for line in lines] == [
        f"scenario {i}/{len(scenarios)} {name}" for i, name in enumerate(scenarios, 1)
    ]


#: A parent whose share and whose child's share never end; the child prints its pid.
_PARENT = """
import os, time
from generalist_control.evaluation.forked_shares import fork_map

def share(i):
    if i:
        print(os.getpid(), flush=True)
    time.sleep(600)

fork_map(share, [0, 1])
"""


def _alive(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"


@needs_fork
@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs Linux's /proc")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_a_child_ends_with_its_parent_and_holds_no_pipe_it_does_not_use(sig):
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        held = [os.readlink(f"/proc/{child}/fd/{f}") for f in os.listdir(f"/proc/{child}/fd")
                if int(f) > 2]  # fmt: skip
        # its own write end, nothing else: no read end it could wait on forever
        assert sum(p.startswith("pipe:") for p in held) == 1, held
        parent.send_signal(sig)
        parent.wait(timeout=60)
        deadline = time.monotonic() + 10
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the forked child outlived its parent"
    finally:
        parent.kill()
        parent.wait()
        if parent.stdout is not None:
            parent.stdout.close()
