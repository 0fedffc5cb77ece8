"""Shares of a piece of work run side by side: one here, the others in forked children.

The loop is Python as much as arithmetic, so a second core helps only through a second
process. A child dies with this process, holds no pipe end it does not use, and leaves
SIGINT to this process, which stops it.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pickle
import signal
import sys
import traceback
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

__all__ = ["balanced", "can_fork", "fork_map"]

T = TypeVar("T")
R = TypeVar("R")

#: ``prctl(PR_SET_PDEATHSIG, ...)``: the signal a process gets when its parent ends (Linux).
_PR_SET_PDEATHSIG = 1


def can_fork() -> bool:
    """Whether :func:`fork_map` runs shares in children here (a system with ``fork``)."""
    return hasattr(os, "fork")


def balanced(costs: Sequence[float], parts: int) -> list[list[int]]:
    """Indices of ``costs`` in ``parts`` groups of about equal total cost (empty ones left out).

    The largest cost first, each to the least loaded group; e.g. ``balanced([3, 1, 1, 1], 2)``
    is ``[[0], [1, 2, 3]]``.
    """
    if parts < 1:
        raise ValueError(f"parts must be at least 1, got {parts}")
    groups: list[list[int]] = [[] for _ in range(parts)]
    load = [0.0] * parts
    for i in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
        g = min(range(parts), key=lambda g: (load[g], g))
        groups[g].append(i)
        load[g] += float(costs[i])
    return [sorted(g) for g in groups if g]


def _die_with(parent: int) -> None:
    """In a child: end when ``parent`` does; SIGINT is the parent's to handle, SIGTERM kills."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (AttributeError, OSError):  # not Linux: the closed pipe still ends it
        pass
    if os.getppid() != parent:  # the parent ended before the signal was asked for
        os._exit(1)


def _result(fn: Callable[[Any], Any], item: Any) -> bytes:
    """``("ok", fn(item))`` or ``("error", (exception, traceback))``, pickled."""
    torch = sys.modules.get("torch")
    if torch is not None:  # the parent's OpenMP threads do not exist here: torch runs on one
        torch.set_num_threads(1)
    try:
        return pickle.dumps(("ok", fn(item)), protocol=pickle.HIGHEST_PROTOCOL)
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the parent
        text = traceback.format_exc()
        try:
            payload = pickle.dumps(("error", (exc, text)), protocol=pickle.HIGHEST_PROTOCOL)
            pickle.loads(payload)  # an exception that cannot be rebuilt goes as text
            return payload
        except Exception:  # noqa: BLE001
            err = RuntimeError(f"{type(exc).__name__}: {exc}")
            return pickle.dumps(("error", (err, text)), protocol=pickle.HIGHEST_PROTOCOL)


def _fork(fn: Callable[[Any], Any], item: Any, others: Sequence[int]) -> tuple[int, int]:
    """Fork a child that sends back ``fn(item)`` (closing ``others``); its pid and pipe."""
    parent = os.getpid()
    sys.stdout.flush()
    sys.stderr.flush()
    read, write = os.pipe()
    pid = os.fork()
    if pid:
        os.close(write)
        return pid, read
    code = 1
    try:
        for fd in (read, *others):
            os.close(fd)
        _die_with(parent)
        payload = _result(fn, item)
        with os.fdopen(write, "wb") as out:
            out.write(payload)
        code = 0
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _read(pid: int, read: int) -> tuple[bytes, int]:
    """What child ``pid`` sent (its pipe read to the end and closed) and its exit code."""
    with os.fdopen(read, "rb") as pipe:
        payload = pipe.read()
    return payload, os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def _unpack(payload: bytes, status: int) -> Any:
    """A child's result; its error raised here."""
    if not payload:
        raise RuntimeError(
            f"a forked share of the work ended without a result (exit code {status}); "
            "its error is above"
        )
    kind, value = pickle.loads(payload)
    if kind == "error":
        exc, text = value
        exc.add_note(f"in the forked share of the work:\n{text}")
        raise exc
    return value


def fork_map(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(item) for item in items]``: ``items[0]`` here, each other one in a forked child.

    A child's error is raised here (its traceback as a note); on an error or a signal here,
    the children still running are killed. Without ``fork`` every item runs here.
    """
    if len(items) < 2 or not can_fork():
        return [fn(item) for item in items]
    children: list[tuple[int, int]] = []
    collected = 0
    try:
        for item in items[1:]:
            children.append(_fork(fn, item, [r for _, r in children]))
        out = [fn(items[0])]
        for pid, read in children:
            payload, status = _read(pid, read)
            collected += 1
            out.append(_unpack(payload, status))
        return out
    finally:
        for pid, read in children[collected:]:  # an error or a signal came first
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            with contextlib.suppress(OSError):
                os.close(read)
