"""No credential in what Hydra prints or saves for a job: one callback for every entry point.

Hydra writes the command's overrides and the composed config to ``<run dir>/.hydra/`` (and
``multirun.yaml``) before the job starts, prints ``Error executing job with overrides:
[...]`` and the error itself when it fails, and logs to the console and ``<job>.log``. A
tracking or storage URL typed with its password would show in all of them.
:class:`RedactSecrets`, registered under ``hydra.callbacks`` in ``conf/hydra_settings.yaml``
(which every entry point composes: ``generate``, ``train``, ``evaluate``, ``report``,
``tune`` and the root shims), passes all of it through
:func:`~generalist_control.common.secrets.redact`:

* on job start, the saved ``.hydra/*.yaml`` files are rewritten masked, and every logging
  handler gets a filter that masks each record (message and traceback);
* on job end, the same files again (``multirun.yaml`` too), the job's overrides (the ones
  Hydra prints on failure) and its error, which is replaced by
  :class:`~generalist_control.common.secrets.RedactedError` when any text of it, or of the
  errors it chains, holds a credential.
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

from generalist_control.common.secrets import redact, redact_exception

__all__ = ["RedactSecrets", "RedactingFilter", "redact_log_handlers", "scrub_hydra_files"]


def _hydra_files() -> list[Path]:
    """The config files Hydra saved for this job (and its multirun), if it runs under Hydra."""
    if not HydraConfig.initialized():
        return []
    hc = HydraConfig.get()
    files = []
    if hc.output_subdir is not None:
        files += sorted((Path(hc.runtime.output_dir) / hc.output_subdir).glob("*.yaml"))
    if hc.mode == RunMode.MULTIRUN:
        files.append(Path(hc.sweep.dir) / "multirun.yaml")
    return [f for f in files if f.is_file()]


def scrub_hydra_files() -> None:
    """Rewrite Hydra's saved configs with credentials in URLs masked (``.hydra/*.yaml``)."""
    for path in _hydra_files():
        text = path.read_text()
        clean = redact(text)
        if clean != text:
            path.write_text(clean)


class RedactingFilter(logging.Filter):
    """A logging filter that masks credentials in a record's message and traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Mask the record in place; never drop it."""
        message = record.getMessage()
        clean = redact(message)
        if clean != message:
            record.msg, record.args = clean, None
        if record.exc_info and not record.exc_text:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = redact(record.exc_text)
        return True


def redact_log_handlers() -> None:
    """Add a :class:`RedactingFilter` to every handler of every logger (once)."""
    loggers = [logging.getLogger(), *logging.Logger.manager.loggerDict.values()]
    for logger in loggers:
        for handler in getattr(logger, "handlers", ()):
            if not any(isinstance(f, RedactingFilter) for f in handler.filters):
                handler.addFilter(RedactingFilter())


class RedactSecrets(Callback):
    """Hydra callback: the job's saved configs, log, overrides and error carry no credential."""

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Mask the configs Hydra has just saved; mask every log record from now on."""
        redact_log_handlers()
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
        path = Path(str(config.hydra.sweep.dir)) / "multirun.yaml"
        if path.is_file():
            path.write_text(redact(path.read_text()))
