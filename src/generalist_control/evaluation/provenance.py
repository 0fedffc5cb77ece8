"""Where an evaluation came from: what reproduces (``summary.json``) and what does not.

The date, the machine and MLflow's ids go into the git-ignored ``provenance.json``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from generalist_control.common.secrets import redact

__all__ = ["command", "machine", "provenance", "weights_digest"]


def weights_digest(policy: torch.nn.Module, config: Any) -> str:
    """SHA-256 of a network's config and weights (unlike the file's, blind to its run)."""
    digest = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for name, tensor in sorted(policy.state_dict().items()):
        t = tensor.detach().cpu().contiguous()
        digest.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        digest.update(t.flatten().view(torch.uint8).numpy().tobytes())
    return f"sha256:{digest.hexdigest()}"


def machine() -> str:
    """The machine in a few words: processor, cores, system, Python."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:  # Linux: the model name, as lscpu prints it
            names = [line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, {platform.system()}, Python {platform.python_version()}"
    )


def command(argv: list[str] | None = None) -> str:
    """The command line as typed: ``python -m generalist_control.<stage> ...`` for a stage.

    Examples
    --------
    >>> command(["/x/src/generalist_control/evaluate.py", "experiment=tag_free"])
    'python -m generalist_control.evaluate experiment=tag_free'
    """
    argv = list(sys.argv if argv is None else argv)
    path = Path(argv[0])
    head = f"python {path.name}"
    if path.parent.name == "generalist_control":
        head = f"python -m generalist_control.{path.stem}"
    return " ".join([head, *argv[1:]])


def provenance() -> dict[str, str]:
    """The date (UTC), this machine (:func:`machine`) and the command (credentials masked)."""
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": machine(),
        "command": redact(command()),
    }
