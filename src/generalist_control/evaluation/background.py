"""The evaluation's figures, drawn in a process of their own while the evaluation goes on.

Drawing the figures (:func:`~generalist_control.evaluation.plots.plot_all`) is seconds of
matplotlib that nothing else waits for until the report folder is published. Where the
system can fork (Linux), :func:`figures_beside` forks two children as soon as the
trajectories exist; they share the figures and draw them into a folder of their own while
the parent writes the tables, and :meth:`FigureJob.collect` waits
for them and moves the files where the report wants them. Elsewhere the figures are drawn
at :meth:`FigureJob.collect`, in the process. Either way the files are the same.
"""

from __future__ import annotations

import multiprocessing
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from generalist_control.evaluation.plots import plot_all
from generalist_control.simulation.simulate import Trajectory

__all__ = ["FigureJob", "figures_beside"]

Trajs = Mapping[str, Mapping[str, Mapping[str, Trajectory]]]


class FigureJob:
    """The figures of one evaluation, drawn beside it (see the module docstring).

    ``processes``: how many children share the figures (two: the parent needs little of a
    second core meanwhile).
    """

    def __init__(self, trajs: Trajs, forked: bool = True, processes: int = 2) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="gc-figures-"))
        self.forked = forked and "fork" in multiprocessing.get_all_start_methods()
        self.procs: list[multiprocessing.process.BaseProcess] = []
        self.here: list[Trajs] = []  # drawn at collect() where nothing forks
        for i in range(processes):
            self._start(trajs, (i, processes))

    def _start(self, trajs: Trajs, share: tuple[int, int]) -> None:
        if not self.forked:
            if share[0] == 0:
                self.here.append(trajs)
            return
        ctx = multiprocessing.get_context("fork")
        proc = ctx.Process(target=plot_all, args=(trajs, self.dir, share), daemon=True)
        proc.start()
        self.procs.append(proc)

    def add(self, trajs: Trajs) -> None:
        """Draw the figures of more scenarios too (one more process), e.g. a later one's."""
        self._start(trajs, (0, 1))

    def collect(self, dest: str | Path) -> list[Path]:
        """Wait for the figures and move them into ``dest`` (made); their paths there.

        Raises
        ------
        RuntimeError
            If the drawing process failed (its traceback is on stderr).
        """
        for trajs in self.here:
            plot_all(trajs, self.dir)
        for proc in self.procs:
            proc.join()
            if proc.exitcode != 0:
                raise RuntimeError(
                    f"drawing the evaluation's figures failed (exit code {proc.exitcode}; "
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
        for proc in self.procs:
            if proc.is_alive():
                proc.terminate()
                proc.join()
        shutil.rmtree(self.dir, ignore_errors=True)


@contextmanager
def figures_beside(trajs: Trajs, enabled: bool = True) -> Iterator[FigureJob | None]:
    """A :class:`FigureJob` for ``trajs`` (None if not ``enabled``), closed on exit."""
    if not enabled:
        yield None
        return
    job = FigureJob(trajs)
    try:
        yield job
    finally:
        job.close()
