"""No credential in what Hydra prints or saves: one callback for every entry point.

Saved configs (``.hydra/*.yaml``, ``multirun.yaml``), a failed job's overrides and error, and
every log record (masked when made, so no handler set up later escapes) are redacted.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

from generalist_control.common.jsonsafe import write_text_atomic
from generalist_control.common.secrets import redact, redact_exception

__all__ = ["RedactSecrets", "redact_log_records", "redact_record", "scrub_hydra_files"]


def _scrub(*paths: Path) -> None:
    """Rewrite each existing file of ``paths`` masked, through a temporary file."""
    for path in paths:
        text = path.read_text() if path.is_file() else ""
        if redact(text) != text:
            write_text_atomic(path, redact(text))


def scrub_hydra_files() -> None:
    """Rewrite the configs Hydra saved for this job (and its multirun), if any, masked."""
    if not HydraConfig.initialized():
        return
    hc = HydraConfig.get()
    if hc.output_subdir is not None:
        _scrub(*sorted((Path(hc.runtime.output_dir) / hc.output_subdir).glob("*.yaml")))
    if hc.mode == RunMode.MULTIRUN:
        _scrub(Path(hc.sweep.dir) / "multirun.yaml")


def redact_record(record: logging.LogRecord) -> logging.LogRecord:
    """Mask ``record``'s message, traceback and stack text in place; return it."""
    try:
        message = record.getMessage()
    except Exception:  # a bad format string: logging reports it when the record is emitted
        return record
    clean = redact(message)
    if clean != message:
        record.msg, record.args = clean, None
    if record.exc_info and not record.exc_text:
        record.exc_text = logging.Formatter().formatException(record.exc_info)
    if record.exc_text:
        record.exc_text = redact(record.exc_text)
    if record.stack_info:
        record.stack_info = redact(record.stack_info)
    return record


def redact_log_records() -> None:
    """Mask every log record of this process from now on, whichever handler emits it (once)."""
    make = logging.getLogRecordFactory()
    if getattr(make, "redacts", False):
        return

    def redacting_factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        return redact_record(make(*args, **kwargs))

    redacting_factory.redacts = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(redacting_factory)


class RedactSecrets(Callback):
    """Hydra callback: the job's saved configs, log, overrides and error carry no credential."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Mask every log record of the run."""
        redact_log_records()

    on_multirun_start = on_run_start  # the launcher's "#0 : <overrides>" lines

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Mask the configs Hydra has just saved; mask every log record (a launcher's worker)."""
        redact_log_records()
        scrub_hydra_files()

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """Mask the files again, and the overrides and error Hydra prints for a failed job."""
        scrub_hydra_files()
        job_return.overrides = redact(list(job_return.overrides or []))
        if job_return.status == JobStatus.FAILED:
            # the public ``return_value`` getter prints the overrides and raises the error
            error = job_return._return_value
            if isinstance(error, BaseException):
                job_return.return_value = redact_exception(error)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Mask ``multirun.yaml`` (saved after the sweep started)."""
        _scrub(Path(str(config.hydra.sweep.dir)) / "multirun.yaml")
