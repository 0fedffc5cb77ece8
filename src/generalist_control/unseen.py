"""The held-out protocol's last step: ``python -m generalist_control.unseen``.

Run by ``beyond/dvc.yaml:unseen`` after its trainings without ``held_out``; the work is
:func:`generalist_control.reports.held_out.run_unseen` (``docs/pipeline.md``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from generalist_control.adaptation.request import AdaptRequest, read_request
from generalist_control.common.sections import as_dict
from generalist_control.common.stage_main import stage_main
from generalist_control.common.stop_signals import exiting_on_signals
from generalist_control.evaluation.eval_config import read_evaluation
from generalist_control.plants.catalog import available_plants
from generalist_control.reports.held_out import ROUTES, UnseenSettings, run_unseen

__all__ = ["main", "read_unseen", "requests", "run"]


def requests(cfg: DictConfig) -> dict[str, AdaptRequest]:
    """Each held-out plant's adaptation (into ``<unseen.models>/adapted/<plant>``), checked.

    Raises
    ------
    ValueError
        If ``held_out`` is empty or names a plant the catalogue does not hold.
    """
    plain: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    held = [str(name) for name in plain["held_out"] or []]
    if not held:
        raise ValueError("held_out is empty: name the held-out plants (conf/unseen.yaml)")
    unknown = sorted(set(held) - set(available_plants()))
    if unknown:
        raise ValueError(
            f"held_out names {unknown}, which conf/plants does not hold; known: "
            f"{', '.join(available_plants())}"
        )
    adapted = Path(plain["unseen"]["models"]) / "adapted"
    return {name: read_request({**plain, "plant": name}, adapted / name) for name in held}


def _routes(names: list[str] | None) -> tuple[str, ...]:
    """``unseen.routes`` checked against :data:`~generalist_control.reports.held_out.ROUTES`."""
    chosen = tuple(str(n) for n in names or ())
    unknown = sorted(set(chosen) - set(ROUTES))
    if unknown:
        raise ValueError(
            f"unseen.routes names {unknown}: the routes are {list(ROUTES)} ([]: none; in "
            "context is the tag-free policy's zero_shot, always evaluated)"
        )
    return chosen


def read_unseen(cfg: DictConfig) -> UnseenSettings:
    """The stage's settings, read once (every key from ``conf/unseen.yaml``)."""
    unseen = as_dict(cfg.unseen)
    return UnseenSettings(
        reports_dir=Path(cfg.paths.reports_dir),
        models=Path(unseen["models"]),
        trained_with=Path(unseen["trained_with"]),
        routes=_routes(unseen["routes"]),
        family_draw=unseen["family_draw"],
        bar=unseen["bar"],
        routes_bar=unseen["routes_bar"],
        evaluation=read_evaluation(as_dict(cfg.evaluation)),
        data=as_dict(cfg.data),
        logger=as_dict(cfg.logger),
    )


def run(cfg: DictConfig) -> dict[str, Any]:
    """Adapt to and evaluate on every held-out plant; return the summary."""
    return run_unseen(read_unseen(cfg), requests(cfg))


@stage_main("unseen")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the held-out protocol's evaluation (SIGTERM: exit 143)."""
    with exiting_on_signals("unseen: stopped"):
        run(cfg)


if __name__ == "__main__":
    main()
