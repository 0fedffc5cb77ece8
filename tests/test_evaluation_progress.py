"""Evaluation says how far it got: a bar on a terminal, a log line with counts per scenario."""

from __future__ import annotations

import logging

from generalist_control.evaluation.runner import evaluate
from generalist_control.plants.catalog import load_plant
from test_evaluate import PLANTS, SCENARIOS, LQIRuntime

#: Two short scenarios, the second on one plant only.
SHORT = {
    "step": {**SCENARIOS["step"], "duration": 2.0},
    "sine": {**SCENARIOS["sine"], "duration": 2.0, "plants": ["cstr"]},
    "nothing_here": {**SCENARIOS["step"], "duration": 2.0, "plants": ["unstable"]},
}


def _run(**kwargs):
    return evaluate(LQIRuntime(PLANTS), [load_plant(n) for n in PLANTS], SHORT, **kwargs)


def test_one_log_line_per_scenario_with_its_counts(caplog):
    with caplog.at_level(logging.INFO, logger="generalist_control.evaluation.loop_layout"):
        _, trajs = _run()
    lines = [r.getMessage() for r in caplog.records if r.name.endswith("evaluation.loop_layout")]
    assert len(lines) == 2, lines  # a scenario without plants runs nothing and says nothing
    assert lines[0].startswith("scenario 1/2 step: 2 plants, 3 controllers, ")
    assert lines[1].startswith("scenario 2/2 sine: 1 plants, 3 controllers, ")
    assert set(trajs) == {"step", "sine"}
    assert set(trajs["sine"]["GC"]) == {"cstr"}


def test_the_bar_shows_on_request_and_not_off_a_terminal(capsys):
    _run(progress=True)
    err = capsys.readouterr().err
    assert "evaluate" in err and "2/2" in err and "scenario" in err
    _run()  # default: only on a terminal; pytest's captured stderr is none
    assert capsys.readouterr().err == ""
