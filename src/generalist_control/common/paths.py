"""Locations the package needs: ``conf/`` (``GC_CONF_DIR`` overrides it) and stage commands."""

from __future__ import annotations

import os
from datetime import datetime
from pathlib import Path

from hydra.core.hydra_config import HydraConfig

__all__ = ["CONF_DIR", "GENERATE_COMMAND", "TRAIN_COMMAND", "conf_dir", "stage_dir"]

#: ``conf/`` beside ``src/`` in the source tree.
CONF_DIR = Path(__file__).resolve().parents[3] / "conf"

#: The command that creates the demonstration dataset (quoted in missing-data errors).
GENERATE_COMMAND = "python -m generalist_control.generate  (or: dvc repro generate)"

#: The command that trains the default policy (quoted in missing-model errors).
TRAIN_COMMAND = "python train.py  (or: dvc repro train)"


def conf_dir() -> Path:
    """The Hydra config directory, honouring ``GC_CONF_DIR``."""
    path = Path(os.environ.get("GC_CONF_DIR", CONF_DIR))
    if not (path / "config.yaml").is_file():
        raise FileNotFoundError(
            f"no Hydra config found at {path}/config.yaml; install the package from a source "
            "checkout (pip install -e .) or set GC_CONF_DIR to a copy of conf/"
        )
    return path


def stage_dir(stage: str) -> Path:
    """The command's output folder: Hydra's, else a new ``outputs/<stage>/<time>``."""
    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path("outputs") / stage / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
