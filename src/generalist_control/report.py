"""The ablation report: ``python -m generalist_control.report`` (``ablation/dvc.yaml``)."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from generalist_control.common.sections import as_dict, read_section
from generalist_control.common.stage_main import stage_main
from generalist_control.reports.ablation import build_report
from generalist_control.reports.report_settings import ReportJob, ReportSettings

__all__ = ["main", "read_job", "run"]


def read_job(cfg: DictConfig) -> ReportJob:
    """The report's settings (``report``) and what it reads of other groups, checked.

    Raises
    ------
    ValueError
        Naming the key: a value of the wrong type, an unknown or a missing key.
    """
    node = as_dict(cfg.report)
    if isinstance(node.get("parent_run"), str | int):
        node["parent_run"] = [str(node["parent_run"])]
    settings = read_section(ReportSettings, node, "report")
    plants = settings.plants
    if plants is None and cfg.closed_loop is not None:
        plants = cfg.closed_loop.systems
    return ReportJob(
        report=settings,
        logger=as_dict(cfg.logger),
        plants=tuple(str(p) for p in plants or ()),
        bar=as_dict(cfg.evaluation.quality_bar),
        threads=int(cfg.threads),
    )


def run(cfg: DictConfig) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow."""
    return build_report(read_job(cfg))


@stage_main("config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the report."""
    run(cfg)


if __name__ == "__main__":
    main()
