"""What an evaluation's ``summary.json`` says of where it came from: the policy, when, where.

``policy``: the source it was given, the MLflow run that trained it and the SHA-256 of the
file evaluated, so two evaluations written to one folder can be told apart.
``provenance``: the date, the machine and the command, which the generated results page
(:mod:`generalist_control.reports.results_page`) prints beside each recipe's figures.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from generalist_control.common.secrets import redact

__all__ = ["command", "machine", "policy_record", "provenance"]


def policy_record(source: str, path: Path, meta: Mapping[str, Any]) -> dict[str, Any]:
    """The evaluated policy: ``source`` as given (credentials masked), its run, its file."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    run_id = meta.get("mlflow_run_id")
    return {
        "source": redact(str(source)),
        "mlflow_run_id": str(run_id) if run_id else None,
        "sha256": f"sha256:{digest}",
    }


def machine() -> str:
    """The machine in a few words: processor, cores, system, Python (``AMD EPYC, 2 cores``)."""
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
