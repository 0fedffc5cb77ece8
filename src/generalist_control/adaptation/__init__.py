"""Adding a plant to a trained policy without retraining: learn its row, nothing else.

Everything is read and checked first; the run folder, MLflow run and model version are
written last (docs/training.md, "Adding a plant to a trained policy").
"""

from __future__ import annotations

import logging
import time
from typing import Any

from generalist_control.adaptation import run_folder
from generalist_control.adaptation.job import learn, prepare
from generalist_control.adaptation.request import AdaptRequest
from generalist_control.common.atomic import check_replaceable, folder_lock

__all__ = ["AdaptationDiverged", "adapt"]

log = logging.getLogger(__name__)


class AdaptationDiverged(ValueError):
    """The adapted policy's closed loop diverges: nothing is written or registered."""


def adapt(request: AdaptRequest) -> tuple[dict[str, Any], dict[str, Any]]:
    """Add ``request.plant`` to ``request.policy``: learn its row, write the policy, log the run.

    Every check runs before anything is written, under a lock on ``run_dir``.

    Returns
    -------
    record : dict
        What was done and measured (also ``<run_dir>/adapt.json``).
    objects : dict
        ``policy``, ``meta``, ``policy_path``, ``run_id``, ``experiment``,
        ``registered_version``, ``base_version``.

    Raises
    ------
    AdaptationDiverged
        If the kept row's closed loop diverges on ``closed_loop_val``'s steps.
    """
    start = time.perf_counter()
    with folder_lock(request.run_dir, "adaptation", wait=False):
        check_replaceable(request.run_dir, {}, run_folder.SETTING)
        job = prepare(request)
        policy, meta, record = learn(job)
        if job.score.diverges(policy, meta):
            source = f" and the recording {request.demos}" if request.demos else ""
            raise AdaptationDiverged(
                f"plant '{job.new.name}': the adapted policy's closed loop diverges (steps "
                f"{list(request.scoring.amplitudes)} from rest, row kept: "
                f"{record['closed_loop']['kept_from']}); nothing was written or registered. "
                f"A row alone cannot control it from these demonstrations: check "
                f"{job.new.path}{source} (units, signs, dt), or train a policy with the plant"
            )
        record["wall_s"] = time.perf_counter() - start
        objects = run_folder.publish(job, policy, meta, record)
    log.info(run_folder.end_message(job, objects))
    return record, {"policy": policy, "meta": meta, **objects}
