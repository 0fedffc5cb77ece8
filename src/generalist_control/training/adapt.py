"""Adding a plant to a trained policy without retraining: learn its row, nothing else.

:func:`prepare` reads and checks everything before anything is written (the policy's recipe,
the plant, the demonstrations); :func:`learn` grows the policy by one tag
(:func:`~generalist_control.model.grow.grow_policy`), starts the new row (``adapt.init``),
fits it on the plant's windows and runs DAgger rounds on the plant with its LQI expert
(:mod:`.row_fit`); :func:`adapt` (``python -m generalist_control.adapt``) then writes the
policy and logs the run (:mod:`.adapt_outputs`). ``docs/training.md``, "Adding a plant to a
trained policy".
"""

from __future__ import annotations

import logging
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from generalist_control.common.configs import as_dict
from generalist_control.common.paths import conf_dir
from generalist_control.common.schema import require_int
from generalist_control.common.secrets import redact
from generalist_control.common.settings import read_section
from generalist_control.data.generation import enabled_families
from generalist_control.data.windows import Windows
from generalist_control.deploy.policy_source import resolve
from generalist_control.model.grow import (
    ROWS,
    RecipeError,
    check_growable,
    free_rows,
    grow_policy,
    plant_scales,
    set_row,
    start_rows,
    with_scales,
)
from generalist_control.model.plant import InferredPlant
from generalist_control.model.policy import POLICY_FILE, Policy, load_policy
from generalist_control.plants.variants import DEFAULT_RANGE
from generalist_control.tracking import mlflow_utils
from generalist_control.training import adapt_outputs
from generalist_control.training.adapt_job import AdaptJob
from generalist_control.training.datamodule import WindowTensors
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.newplant import (
    NewPlant,
    generated_windows,
    load_new_plant,
    plant_meta,
    retagged,
)
from generalist_control.training.recorded import read_recorded
from generalist_control.training.row_fit import (
    closed_loop,
    dagger_round,
    fit_row,
    learned_parameters,
    nearest_row,
)
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import (
    AdaptSettings,
    ClosedLoopValSettings,
    DaggerSettings,
)

__all__ = ["AdaptJob", "adapt", "learn", "prepare"]

log = logging.getLogger(__name__)


def _plain(cfg: DictConfig, key: str) -> Any:
    node = OmegaConf.select(cfg, key)
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _run_dir(cfg: DictConfig) -> Path:
    """``run_dir``, Hydra's output folder (``outputs/adapt/<time>``), or a new one."""
    if cfg.get("run_dir"):
        return Path(cfg.run_dir)
    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path("outputs/adapt") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def _row_for(policy: Policy, meta: dict[str, Any], new: NewPlant, learn: bool) -> int:
    """The row the plant gets: a new one, or (tag-free, nothing learned) a free one."""
    if not isinstance(policy.net.plant, InferredPlant) or learn:
        check_growable(policy)
        return policy.net.n_tags
    free = free_rows(policy, meta["tags"].values())
    if not free:
        raise RecipeError(
            f"every one of the tag-free policy's {policy.net.n_tags} normaliser rows is a "
            "trained plant's: none is free for the new plant's scales; retrain it with a "
            "larger model.plant.n_tags"
        )
    return new.file_tag if new.file_tag in free else free[0]


def _windows(
    cfg: DictConfig, new: NewPlant, policy: Policy
) -> tuple[Windows, dict[str, Any], bool]:
    """The plant's windows: recorded (``demos=``) or generated from its LQI expert."""
    history, horizon, channels = policy.history, policy.horizon, policy.channels
    if cfg.get("demos"):
        rec = read_recorded(
            cfg.demos, new.plant, new.plant.tag, history, horizon, "previous_control" in channels
        )
        facts = {
            "source": str(cfg.demos),
            "expert": "recorded",
            "trajectories": rec.trajectories,
            "windows": len(rec.windows),
        }
        return rec.windows, facts, True
    windows, facts = generated_windows(new.plant, as_dict(cfg.data), history, horizon, channels)
    return windows, facts, False


def _dagger(
    cfg: DictConfig, new: NewPlant, policy: Policy, seed: int
) -> tuple[RolloutSampler, ExpertLabeller]:
    """The training's sampler (on the new plant alone) and labeller (``dagger``'s settings)."""
    node = _plain(cfg, "dagger")
    if node is None:  # the recipe's rounds off: adapt's own rounds take conf/'s settings
        node = OmegaConf.to_container(OmegaConf.load(conf_dir() / "config.yaml").dagger)
    spec = read_section(DaggerSettings, node, "dagger")
    data = as_dict(cfg.data)
    block = data.get("variants") or {}
    sampler = RolloutSampler(
        [new.plant],
        spec.sampler,
        limit=float(data["amplitudes"]["limit"]),
        families=enabled_families(data),
        seed=seed,
        variant_range=float(block.get("range", DEFAULT_RANGE)),
        variant_tries=int(block.get("max_tries", 10)),
    )
    labeller = ExpertLabeller(spec.labeller, policy.history, policy.horizon, policy.channels)
    return sampler, labeller


def prepare(cfg: DictConfig) -> AdaptJob:
    """Read and check the adaptation's config; load the policy, the plant and its windows.

    Nothing is written and no run is opened.

    Raises
    ------
    ValueError
        Naming the fix: an ``adapt`` setting out of range, a policy whose recipe cannot take
        a row (:class:`~generalist_control.model.grow.RecipeError`), a plant refused by
        :func:`~.newplant.load_new_plant`, unusable recorded demonstrations
        (:class:`~.recorded.RecordingError`), an ``adapt.unfreeze`` name the policy lacks.
    """
    settings = read_section(AdaptSettings, _plain(cfg, "adapt"), "adapt")
    seed = require_int("seed", _plain(cfg, "seed"), minimum=0)
    torch.set_num_threads(require_int("threads", _plain(cfg, "threads")))
    if not cfg.get("plant"):
        raise ValueError("plant= is required: a catalogue name or the path of a plant YAML")
    source = str(cfg.get("policy") or Path(cfg.paths.models_dir) / POLICY_FILE)
    if source.startswith(("runs:/", "models:/")):  # the store is touched for these only
        mlflow_utils.set_tracking(cfg.logger)
    path = resolve(source)
    policy, meta = load_policy(path)
    if settings.learn:
        check_growable(policy, source)
    new = load_new_plant(str(cfg.plant), meta, float(meta["dt"]))
    new = retagged(new, _row_for(policy, meta, new, settings.learn))
    learned_parameters(policy, settings.unfreeze)  # the names checked before any work
    windows, demos, recorded = _windows(cfg, new, policy)
    sampler, labeller = _dagger(cfg, new, policy, seed)
    node = _plain(cfg, "closed_loop_val")
    scoring = read_section(ClosedLoopValSettings, node or {}, "closed_loop_val")
    run_dir = _run_dir(cfg)
    adapt_outputs.check_run_dir(run_dir)
    return AdaptJob(
        settings, new, policy, meta, source, path, windows, demos,
        None if recorded else sampler, labeller, scoring, seed, run_dir,
    )  # fmt: skip


def _start(job: AdaptJob, tensors: dict[str, torch.Tensor]) -> tuple[Policy, dict[str, Any]]:
    """The grown policy, its new row at its start (``adapt.init``), and how it was chosen."""
    scales = plant_scales(tensors["state"], tensors["mask"], tensors["ref"], tensors["target"])
    tags = {str(k): int(v) for k, v in job.meta["tags"].items()}
    candidates = start_rows(job.policy, tags.values())
    rows = job.policy.state_dict()[ROWS]
    candidates.update({name: rows[t] for name, t in tags.items()})
    grown = grow_policy(job.policy, candidates["mean"], scales)
    tag = job.new.plant.tag
    chosen, losses = "mean", dict[str, float]()
    if job.settings.init == "nearest":
        chosen, losses = nearest_row(grown, tag, tensors, candidates)
        set_row(grown, tag, candidates[chosen])
    return grown, {"mode": job.settings.init, "chosen": chosen, "losses": losses}


def _meta(job: AdaptJob, record: dict[str, Any]) -> dict[str, Any]:
    """The adapted policy's meta: the plant added, with what it was adapted from."""
    base = {
        "source": redact(job.source),
        "mlflow_run_id": job.meta.get("mlflow_run_id"),
        "n_tags": job.policy.net.n_tags,
    }
    keep = ("tag", "file_tag", "demonstrations", "learned")
    facts = {"base": base, "init": record["init"]["chosen"], **{k: record[k] for k in keep}}
    return plant_meta(job.meta, job.new.plant, facts)


def _name_only(job: AdaptJob, tensors: dict[str, torch.Tensor]) -> tuple[Policy, dict[str, Any]]:
    """A tag-free policy named for the plant: its scales on a free row, nothing learned."""
    scales = plant_scales(tensors["state"], tensors["mask"], tensors["ref"], tensors["target"])
    return with_scales(job.policy, job.new.plant.tag, scales), {"mode": "none", "chosen": None}


def _snapshot(policy: Policy, tag: int, learned: dict[str, torch.nn.Parameter]) -> dict:
    """The row ``tag`` and the ``learned`` parameters, copied."""
    keep = {"row": policy.state_dict()[ROWS][tag].clone()}
    return keep | {k: p.detach().clone() for k, p in learned.items()}


def _rounds(
    job: AdaptJob, policy: Policy, meta: dict[str, Any], data: WindowTensors, first: float
) -> dict[str, Any]:
    """DAgger rounds and fits after the first fit; the best row (and learned) restored.

    The row kept is the one whose closed loop is nearest LQI's, the first fit's included.
    With recorded demonstrations (no sampler) there are no rounds: the first fit is kept.
    """
    s, plant, tag, sampler = job.settings, job.new.plant, job.new.plant.tag, job.sampler
    if sampler is None:
        return {"rounds": [], "kept": first, "dagger_windows": 0, "losses": []}
    learned = learned_parameters(policy, s.unfreeze)
    keep = _snapshot(policy, tag, learned)
    best, scores, added, losses = first, [], 0, []
    for i in range(s.rounds):
        added += dagger_round(policy, meta, sampler, job.labeller, data, i, s.beta_at(i))
        losses += fit_row(policy, tag, data.tensors, s, learned, job.seed + i + 1)
        scores.append(closed_loop(policy, meta, plant, job.scoring))
        if scores[-1] <= best:
            best, keep = scores[-1], _snapshot(policy, tag, learned)
    set_row(policy, tag, keep["row"])
    with torch.no_grad():
        for k, p in learned.items():
            p.copy_(keep[k])
    return {"rounds": scores, "kept": best, "dagger_windows": added, "losses": losses}


def learn(job: AdaptJob) -> tuple[Policy, dict[str, Any], dict[str, Any]]:
    """The adapted policy, its meta, and the adaptation's record (scores, losses, windows)."""
    data = WindowTensors(job.windows)
    s, plant, tag = job.settings, job.new.plant, job.new.plant.tag
    named = isinstance(job.policy.net.plant, InferredPlant)
    policy, init = (_name_only if named else _start)(job, data.tensors)
    learned = [] if named or not s.learn else [f"{ROWS}[{tag}]", *s.unfreeze]
    record: dict[str, Any] = {
        "plant": plant.name, "tag": tag, "file_tag": job.new.file_tag,
        "plant_file": str(job.new.path), "demonstrations": dict(job.demos),
        "learned": learned, "init": init,
    }  # fmt: skip
    meta = _meta(job, record)
    score = closed_loop(policy, meta, plant, job.scoring)
    record["closed_loop"] = {"start": score, "kept": score}
    if s.learn and not named:
        learned_now = learned_parameters(policy, s.unfreeze)
        losses = fit_row(policy, tag, data.tensors, s, learned_now, job.seed)
        fitted = closed_loop(policy, meta, plant, job.scoring)
        more = _rounds(job, policy, meta, data, fitted)
        record["closed_loop"].update(fit=fitted, rounds=more["rounds"], kept=more["kept"])
        record["loss"] = [*losses, *more["losses"]]
        record["demonstrations"]["dagger_windows"] = more["dagger_windows"]
    if job.sampler is None and not named:  # recorded: the recorded controller is the baseline
        u, _ = policy.predict_windows(job.windows)
        target = np.asarray(job.windows.target, dtype=np.float64)
        err = float(np.mean((u - target) ** 2) / max(float(np.mean(target**2)), 1e-300))
        record["recorded_relative_mse"] = err
    meta = _meta(job, record)
    return policy, meta, record


def adapt(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Add ``cfg.plant`` to ``cfg.policy``: learn its row, write the policy, log the run.

    Returns
    -------
    record : dict
        What was done and measured (also ``<run_dir>/adapt.json``): the plant and its row,
        the demonstrations, the start row chosen, closed-loop scores against LQI (start,
        after the fit, after each DAgger round, kept), losses, ``wall_s``.
    objects : dict
        ``policy``, ``meta``, ``policy_path``, ``run_id``, ``experiment``,
        ``registered_version``, ``base_version``.
    """
    start = time.perf_counter()
    job = prepare(cfg)
    policy, meta, record = learn(job)
    record["wall_s"] = time.perf_counter() - start
    objects = adapt_outputs.publish(job, policy, meta, record, cfg)
    log.info(adapt_outputs.end_message(job, objects, cfg))
    return record, {"policy": policy, "meta": meta, **objects}
