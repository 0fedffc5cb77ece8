"""The evaluation's figures, drawn in processes of their own while the evaluation goes on.

Drawing the figures (:func:`~generalist_control.evaluation.plots.plot_all`) is seconds of
matplotlib that nothing else waits for until the report folder is published. Where the
system can fork (Linux), a :class:`FigureJob` forks its drawing process when it is made,
before the trajectories exist: that process imports pyplot and builds the step and sine
sheet (:func:`~generalist_control.evaluation.plots.warm_up`) while the evaluation works,
then waits. :meth:`FigureJob.draw` sends it what the figures show
(:func:`~generalist_control.evaluation.plots.plotted`, a few MB); it forks a second drawer,
the two share the figures and draw them into a folder of their own while the evaluation
writes its tables, and :meth:`FigureJob.collect` waits for them and moves the files where the
report wants them. Elsewhere the figures are drawn at :meth:`FigureJob.collect`, in the
process. Either way the files are the same.

The stage's own command makes its job earlier still (:func:`start_early`, after its
imports): the drawing process then makes ready while Hydra composes the config, when the
second core has nothing else to do; :func:`figures_beside` takes that job over.
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import shutil
import signal
import sys
import tempfile
import traceback
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from multiprocessing.connection import Connection
from pathlib import Path

from generalist_control.evaluation.plots import plot_all, plotted, warm_up
from generalist_control.simulation.simulate import Trajectory

__all__ = ["FigureJob", "figures_beside", "start_early"]

Trajs = Mapping[str, Mapping[str, Mapping[str, Trajectory]]]

#: A job made by :func:`start_early`, not yet taken by :func:`figures_beside`.
_early: FigureJob | None = None


def _draw(trajs: Trajs, out: Path, share: tuple[int, int]) -> int:
    """Draw one share of the figures; 0, or 1 with the traceback on stderr."""
    try:
        plot_all(trajs, out, share)
        return 0
    except BaseException:  # noqa: BLE001 - reported by the exit code, printed here
        traceback.print_exc()
        return 1
    finally:
        sys.stderr.flush()


def _serve(recv: Connection, send: Connection, out: Path, processes: int) -> None:
    """The drawing process: make ready, wait for the trajectories, draw them in shares."""
    send.close()  # the evaluation's end: only the evaluation may hold it
    warm_up()
    try:
        trajs = recv.recv()
    except EOFError:  # the evaluation ended, or wanted no figures
        shutil.rmtree(out, ignore_errors=True)
        return
    sys.stdout.flush()
    sys.stderr.flush()
    children: list[int] = []

    def stop(*_: object) -> None:  # FigureJob.close: the drawers stop too
        for pid in children:
            os.kill(pid, signal.SIGKILL)
        os._exit(1)

    signal.signal(signal.SIGTERM, stop)
    for i in range(1, processes):
        pid = os.fork()
        if pid == 0:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os._exit(_draw(trajs, out, (i, processes)))
        children.append(pid)
    failed = _draw(trajs, out, (0, processes))
    for pid in children:
        failed |= os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) != 0
    if failed:
        sys.exit(1)


class FigureJob:
    """The figures of one evaluation, drawn beside it (see the module docstring).

    ``processes``: how many processes share the figures (two: the evaluation needs little
    of a second core meanwhile).
    """

    def __init__(self, forked: bool = True, processes: int = 2) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="gc-figures-"))
        self.forked = forked and "fork" in multiprocessing.get_all_start_methods()
        self.here: Trajs | None = None  # drawn at collect() where nothing forks
        self.proc: multiprocessing.process.BaseProcess | None = None
        if self.forked:
            ctx = multiprocessing.get_context("fork")
            recv, self._send = ctx.Pipe(duplex=False)
            self.proc = ctx.Process(
                target=_serve, args=(recv, self._send, self.dir, processes), daemon=True
            )
            self.proc.start()
            recv.close()

    def draw(self, trajs: Trajs) -> None:
        """Draw the figures of ``trajs`` (once per job)."""
        if self.proc is None:
            self.here = trajs
            return
        self._send.send(plotted(trajs))
        self._send.close()

    def collect(self, dest: str | Path) -> list[Path]:
        """Wait for the figures and move them into ``dest`` (made); their paths there.

        Raises
        ------
        RuntimeError
            If the drawing failed (its traceback is on stderr), or nothing was drawn.
        """
        if self.proc is None:
            if self.here is None:
                raise RuntimeError("FigureJob.collect before FigureJob.draw")
            plot_all(self.here, self.dir)
        else:
            if not self._send.closed:
                raise RuntimeError("FigureJob.collect before FigureJob.draw")
            self.proc.join()
            if self.proc.exitcode != 0:
                raise RuntimeError(
                    f"drawing the evaluation's figures failed (exit code {self.proc.exitcode}; "
                    "its traceback is above)"
                )
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        moved = []
        for path in sorted(self.dir.iterdir()):
            moved.append(Path(shutil.move(str(path), str(dest / path.name))))
        return moved

    def close(self) -> None:
        """Stop the drawing if it still runs; remove its folder."""
        if self.proc is not None:
            self._send.close()
            if self.proc.is_alive():
                self.proc.terminate()
            self.proc.join()
        shutil.rmtree(self.dir, ignore_errors=True)


def start_early() -> None:
    """Make the next :func:`figures_beside`'s job now: its process makes ready meanwhile.

    A job no :func:`figures_beside` took is closed when this process exits (e.g. after
    an error in the config).
    """
    global _early
    if _early is None:
        _early = FigureJob()
        atexit.register(_close_early)


def _close_early() -> None:
    global _early
    job, _early = _early, None
    if job is not None:
        job.close()


@contextmanager
def figures_beside(enabled: bool = True) -> Iterator[FigureJob | None]:
    """A :class:`FigureJob` (None if not ``enabled``), closed on exit.

    The job made by :func:`start_early`, if any (closed here if not ``enabled``).
    """
    global _early
    job, _early = _early, None
    if not enabled:
        if job is not None:
            job.close()
        yield None
        return
    if job is not None and job.proc is not None and not job.proc.is_alive():
        job.close()  # its drawing process is gone (e.g. killed): its folder goes too
        job = None
    job = job if job is not None else FigureJob()
    try:
        yield job
    finally:
        job.close()
