"""The runtime's weak answers of issue 36.

* building the TorchScript or ONNX backend leaves nothing in the temporary directory (each
  load left a ``tmp*/policy.*`` folder behind).
"""

from __future__ import annotations

import tempfile

import numpy as np
import pytest
import torch

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from helpers import policy_meta

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3


@pytest.fixture(scope="module")
def policy() -> tuple[Policy, dict]:
    """A small integrating policy (random weights; the checks do not depend on them)."""
    torch.manual_seed(0)
    config = {"hidden": 8, "experts": 2, "window_scale": 1, "integral": 1, "linear_skip": 1}
    return Policy({**config, "linear_samples": 1}).eval(), policy_meta(PLANTS, 8, 3)


@pytest.mark.parametrize("backend", ["torchscript", "onnx"])
def test_building_a_backend_leaves_nothing_in_the_temporary_directory(
    policy, backend, tmp_path, monkeypatch
):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    rt = PolicyRuntime(*policy, backend=backend)
    rt.reset("cstr")  # one plant: the ONNX backend builds its batch-1 graph too
    rt.step([0.1, 0.0], 1.0)
    rt.reset(list(PLANTS))
    rt.step(np.zeros((2, 4)), np.ones(2))
    assert list(tmp_path.iterdir()) == []
