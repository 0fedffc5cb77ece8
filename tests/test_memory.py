"""keep_freed_memory: a training-like step stops faulting new pages; no glibc, no change."""

from __future__ import annotations

import ctypes
import subprocess
import sys
import textwrap

import pytest
from omegaconf import OmegaConf

from generalist_control.common import memory

# Forward and backward of an LSTM, as a training step does: its tensors are freed and
# allocated again each step.
_STEPS = textwrap.dedent(
    """
    import resource, sys
    from generalist_control.common.memory import keep_freed_memory
    if sys.argv[1] == "keep":
        assert keep_freed_memory() is True
    import torch
    torch.manual_seed(0)
    torch.set_num_threads(1)
    lstm, lin = torch.nn.LSTM(64, 32, batch_first=True), torch.nn.Linear(64, 64)
    opt = torch.optim.Adam([*lstm.parameters(), *lin.parameters()])
    x = torch.randn(1024, 8, 64)
    def step():
        opt.zero_grad()
        y, _ = lstm(lin(x))
        y.pow(2).mean().backward()
        opt.step()
    for _ in range(20):
        step()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(40):
        step()
    print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 40)
    """
)


def _faults_per_step(mode: str) -> float:
    out = subprocess.run(
        [sys.executable, "-c", _STEPS, mode], capture_output=True, text=True, check=True
    )
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_kept_memory_makes_steps_fault_free() -> None:
    # glibc's defaults: about 300-500 new pages a step here; kept: 0-15 (what a step still
    # takes new varies from run to run, hence a ratio)
    default, kept = _faults_per_step("default"), _faults_per_step("keep")
    assert kept * 5 < default, f"{kept} page faults per step kept, {default} by default"


def test_without_mallopt_nothing_is_changed(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_library(name: str | None) -> None:
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", no_library)
    assert memory.keep_freed_memory() is False


def test_train_command_keeps_freed_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    from generalist_control import train

    calls: list[str] = []

    def kept() -> bool:
        calls.append("kept")
        return True

    def trained(cfg: object) -> dict[str, float]:
        calls.append("trained")
        return {"val/loss": 0.5}

    monkeypatch.setattr(train, "keep_freed_memory", kept)
    monkeypatch.setattr(train, "run", trained)

    assert train.main.__wrapped__(OmegaConf.create({})) == 0.5
    assert calls == ["kept", "trained"]
