"""SIGTERM and SIGINT stop a command: it unwinds, its run ``KILLED``, and exits non-zero.

The first signal becomes :class:`Stopped`, a ``KeyboardInterrupt``: joblib kills its workers,
Optuna fails the running trial, and nothing takes it for a job's ordinary failure.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

__all__ = [
    "Stopped",
    "exiting_on_signals",
    "install",
    "received",
    "restore",
    "stopping_on_signals",
]

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGTERM, signal.SIGINT)
_saved: dict[int, Any] = {}
_received: list[int] = []


class Stopped(KeyboardInterrupt):
    """The command received ``signum`` and stops."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


def _handle(signum: int, frame: FrameType | None) -> None:
    """Note the signal; raise :class:`Stopped` at the first."""
    _received.append(signum)
    if len(_received) == 1:  # later signals: the command is stopping already
        log.warning("%s received: stopping", signal.Signals(signum).name)
        raise Stopped(signum)


def install() -> bool:
    """Stop on SIGTERM and SIGINT from now on; False where it cannot (not the main thread)."""
    if _saved or threading.current_thread() is not threading.main_thread():
        return False
    _received.clear()
    for signum in SIGNALS:
        _saved[signum] = signal.signal(signum, _handle)
    return True


def restore() -> None:
    """The handlers from before :func:`install`."""
    for signum, handler in _saved.items():
        signal.signal(signum, signal.SIG_DFL if handler is None else handler)
    _saved.clear()


def received() -> int | None:
    """The first signal received since :func:`install`, if any."""
    return _received[0] if _received else None


@contextmanager
def stopping_on_signals() -> Iterator[None]:
    """:func:`install` for the block (if not installed already), :func:`restore` after it."""
    installed = install()
    try:
        yield
    finally:
        if installed:
            restore()


@contextmanager
def exiting_on_signals(message: str) -> Iterator[None]:
    """:func:`stopping_on_signals` for a command: :class:`Stopped` exits 128 + the signal's number.

    ``message`` (what was left undone) is logged with the signal's name.
    """
    try:
        with stopping_on_signals():
            yield
    except Stopped as stop:
        log.error("%s: %s", stop, message)
        sys.exit(128 + stop.signum)
