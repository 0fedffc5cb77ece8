"""The one stop-signal path (``common.stop_signals``): either signal exits 128 + its number.

adapt, unseen, tune and evaluate stop through :func:`exiting_on_signals`; the evaluation's
own test (tests/test_evaluation_stops.py) sends SIGTERM to the real command, this one sends
both signals to a small command that holds the same context and nothing else.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
#: Stops on a signal inside ``exiting_on_signals``, its ``finally`` run first; else exits 0.
COMMAND = """
import logging, sys, time
logging.basicConfig(stream=sys.stderr, level=logging.INFO)
from generalist_control.common.stop_signals import exiting_on_signals
with exiting_on_signals("nothing was written"):
    try:
        print("ready", flush=True)
        time.sleep(60)
    finally:
        print("unwound", flush=True)
"""


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_either_signal_unwinds_then_exits_128_plus_its_number(sig, status):
    proc = subprocess.Popen(
        [sys.executable, "-c", COMMAND], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env={"PYTHONPATH": str(SRC)},
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == status, err
    assert out == "unwound\n"
    assert f"{sig.name} received: stopping" in err
    assert f"stopped by {sig.name}: nothing was written" in err
