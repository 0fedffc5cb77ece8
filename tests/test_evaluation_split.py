"""The evaluation's plants split over processes: shares, results back in order, errors."""

from __future__ import annotations

import logging
import os

import numpy as np
import pandas as pd
import pytest

from generalist_control.evaluation import split
from generalist_control.evaluation.runner import run_suite
from generalist_control.evaluation.split import balanced, can_fork, fork_map
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
    monkeypatch.setattr(split.multiprocessing, "get_all_start_methods", lambda: ["spawn"])
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
    with caplog.at_level(logging.INFO, logger="generalist_control.evaluation.plan"):
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
    lines = [r.getMessage() for r in caplog.records if r.name.endswith("evaluation.plan")]
    assert [line.split(":")[0] for line in lines] == [
        f"scenario {i}/{len(scenarios)} {name}" for i, name in enumerate(scenarios, 1)
    ]
