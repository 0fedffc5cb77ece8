"""Work split over processes: shares of the evaluation's plants in loops side by side.

The evaluation's loop is Python per sample and per plant as much as it is the network's
arithmetic, and only one thread at a time runs Python. :func:`fork_map` runs one share of
the work in this process and every other share in a forked child at the same time, so two
cores each run a loop of their own; :func:`balanced` makes the shares about equal. Where
the system cannot fork (or this process is a daemon, which may not have children) every
share runs here, one after the other: the results are the same.
"""

from __future__ import annotations

import multiprocessing
import pickle
import sys
import traceback
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, TypeVar

__all__ = ["balanced", "can_fork", "fork_map"]

T = TypeVar("T")
R = TypeVar("R")


def can_fork() -> bool:
    """Whether :func:`fork_map` runs shares in children here (Linux, not in a daemon)."""
    return (
        "fork" in multiprocessing.get_all_start_methods()
        and not multiprocessing.current_process().daemon
    )


def balanced(costs: Sequence[float], parts: int) -> list[list[int]]:
    """Indices of ``costs`` in ``parts`` groups of about equal total cost.

    The largest cost first, each to the group with the least so far; every group's indices
    in their original order; empty groups left out. E.g. ``balanced([3, 1, 1, 1], 2)`` is
    ``[[0], [1, 2, 3]]``.
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


def _child(fn: Callable[[Any], Any], item: Any, conn: Connection) -> None:
    """Run ``fn(item)`` in the forked child; send back ``("ok", result)`` or the error."""
    torch = sys.modules.get("torch")
    if torch is not None:  # the parent's OpenMP threads do not exist here: torch runs on one
        torch.set_num_threads(1)
    try:
        payload = pickle.dumps(("ok", fn(item)), protocol=pickle.HIGHEST_PROTOCOL)
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the parent
        text = traceback.format_exc()
        try:
            payload = pickle.dumps(("error", (exc, text)), protocol=pickle.HIGHEST_PROTOCOL)
            pickle.loads(payload)  # an exception that cannot be rebuilt goes as text
        except Exception:  # noqa: BLE001
            err = RuntimeError(f"{type(exc).__name__}: {exc}")
            payload = pickle.dumps(("error", (err, text)), protocol=pickle.HIGHEST_PROTOCOL)
    conn.send_bytes(payload)
    conn.close()


def fork_map(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(item) for item in items]``: ``items[0]`` here, each other one in a forked child.

    The children run while this process works on ``items[0]``; their results come back
    pickled. An error in a child is raised here (its traceback added as a note); on any
    error the children still running are stopped.
    """
    if len(items) < 2 or not can_fork():
        return [fn(item) for item in items]
    ctx = multiprocessing.get_context("fork")
    children: list[tuple[Any, Connection]] = []
    try:
        for item in items[1:]:
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(fn, item, send), daemon=True)
            proc.start()
            send.close()
            children.append((proc, recv))
        out = [fn(items[0])]
        for proc, recv in children:
            try:
                status, value = pickle.loads(recv.recv_bytes())
            except EOFError:
                proc.join()
                raise RuntimeError(
                    f"a forked share of the work ended without a result (exit code "
                    f"{proc.exitcode}); its error is above"
                ) from None
            proc.join()
            if status == "error":
                exc, text = value
                exc.add_note(f"in the forked share of the work:\n{text}")
                raise exc
            out.append(value)
        return out
    finally:
        for proc, recv in children:
            recv.close()
            if proc.is_alive():
                proc.terminate()
                proc.join()
