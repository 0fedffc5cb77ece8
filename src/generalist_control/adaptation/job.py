"""An adaptation's work: everything read and checked first (:func:`prepare`), then the row learned.

The row is a parameter of its own, spliced into the embedding (``adapt.unfreeze`` may name a few
parameters besides); the row kept is the one whose closed loop is nearest LQI's, the start
row included. A tag-free policy is only named for the plant (its scales on a free row).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from generalist_control.adaptation.new_plant import (
    NewPlant,
    generated_windows,
    load_new_plant,
    plant_meta,
    read_recorded,
)
from generalist_control.adaptation.request import AdaptRequest, AdaptSettings
from generalist_control.common.secrets import redact
from generalist_control.data.windows import Windows
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.policy_source import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.bank import (
    ROWS,
    RecipeError,
    check_growable,
    grow_policy,
    plant_scales,
    set_row,
    start_rows,
    with_scales,
)
from generalist_control.model.policy import Policy, load_policy, policy_sha256
from generalist_control.plants.definition import Plant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.simulation.simulate import simulate_many
from generalist_control.tracking import mlflow_utils
from generalist_control.training.callbacks import dagger_round
from generalist_control.training.datamodule import WindowTensors
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import ClosedLoopValSettings, rollout_data

__all__ = [
    "AdaptJob",
    "LoopScore",
    "fit_row",
    "learn",
    "learned_parameters",
    "nearest_row",
    "prepare",
]

#: The row's name inside the network (``ROWS`` without ``net.``).
_NET_ROWS = ROWS.removeprefix("net.")

#: Windows the start rows are compared on (a random subset when there are more).
_COMPARED = 4096


def _spliced(frozen: Tensor, tag: int, row: Tensor) -> Tensor:
    """The embedding's weight with row ``tag`` replaced by ``row`` (the others detached)."""
    return torch.cat([frozen[:tag], row[None], frozen[tag + 1 :]])


@torch.no_grad()
def nearest_row(
    policy: Policy, tag: int, tensors: Mapping[str, Tensor], candidates: Mapping[str, Tensor]
) -> tuple[str, dict[str, float]]:
    """The candidate row whose policy imitates the windows best, and every candidate's loss."""
    frozen = policy.state_dict()[ROWS]
    n = len(tensors["tag"])
    pick = torch.randperm(n, generator=torch.Generator().manual_seed(0))[:_COMPARED]
    batch = {k: v[pick] for k, v in tensors.items()}
    losses = {
        name: float(policy.errors(batch, {_NET_ROWS: _spliced(frozen, tag, row)})[0].mean())
        for name, row in candidates.items()
    }
    finite = {k: v for k, v in losses.items() if v == v}
    return min(finite, key=finite.__getitem__), losses


def learned_parameters(policy: Policy, unfreeze: Sequence[str]) -> dict[str, nn.Parameter]:
    """The network's parameters ``unfreeze`` names (each a dotted prefix of their names).

    Raises
    ------
    ValueError
        If a prefix names no parameter, or names the tag embedding (trained rows stay).
    """
    named = dict(policy.named_parameters())
    out: dict[str, nn.Parameter] = {}
    for prefix in unfreeze:
        hits = {k: p for k, p in named.items() if k == prefix or k.startswith(prefix + ".")}
        if not hits:
            parts = sorted({".".join(k.split(".")[:2]) for k in named})
            raise ValueError(
                f"adapt.unfreeze names {prefix!r}, which is no parameter of the policy; its "
                f"parts: {parts} (e.g. net.skip.gains)"
            )
        if ROWS in hits:
            raise ValueError(
                f"adapt.unfreeze names {prefix!r}, which holds the trained plants' rows "
                f"({ROWS}): the new row is always learned, the others never"
            )
        out.update(hits)
    return out


@contextmanager
def _learning(policy: Policy, learned: Mapping[str, nn.Parameter]) -> Iterator[None]:
    """Only ``learned`` parameters take gradients inside; afterwards every one does again."""
    flags = {k: p.requires_grad for k, p in policy.named_parameters()}
    for k, p in policy.named_parameters():
        p.requires_grad_(k in learned)
    was_training = policy.training
    policy.train()
    try:
        yield
    finally:
        for k, p in policy.named_parameters():
            p.requires_grad_(flags[k])
        policy.train(was_training)


def fit_row(
    policy: Policy,
    tag: int,
    tensors: Mapping[str, Tensor],
    settings: AdaptSettings,
    learned: Mapping[str, nn.Parameter],
    seed: int,
) -> list[float]:
    """Fit row ``tag`` (and ``learned``) on ``tensors``; return each epoch's mean loss.

    Every other row and every parameter not in ``learned`` is left bit for bit as it was.
    """
    frozen = policy.state_dict()[ROWS].clone()
    row = nn.Parameter(frozen[tag].clone())
    optimiser = torch.optim.Adam([row, *learned.values()], lr=settings.lr)
    generator = torch.Generator().manual_seed(seed)
    n, losses = len(tensors["tag"]), []
    with _learning(policy, learned):
        for _ in range(settings.epochs):
            total = 0.0
            for idx in torch.randperm(n, generator=generator).split(settings.batch_size):
                batch = {k: v[idx] for k, v in tensors.items()}
                loss = policy.errors(batch, {_NET_ROWS: _spliced(frozen, tag, row)})[0].mean()
                optimiser.zero_grad(set_to_none=True)
                loss.backward()
                optimiser.step()
                total += loss.item() * len(idx)
            losses.append(total / n)
    set_row(policy, tag, row)
    return losses


class LoopScore:
    """The plant's step error in closed loop relative to its LQI's (1: diverged).

    On the steps of ``closed_loop_val``, LQI simulated once.
    """

    def __init__(self, plant: Plant, scoring: ClosedLoopValSettings) -> None:
        self.plant = plant
        self.steps = ClosedLoopScore([plant], scoring.amplitudes, scoring.duration)

    def __call__(self, policy: Policy, meta: dict[str, Any]) -> float:
        """The score of ``policy`` (lower is better, at most 1)."""
        with torch.inference_mode():
            return self.steps(RuntimeAdapter(PolicyRuntime(policy, meta)))[self.plant.name]

    def diverges(self, policy: Policy, meta: dict[str, Any]) -> bool:
        """Whether a step run of ``policy`` diverges (a state beyond the simulator's bound)."""
        with torch.inference_mode():
            runs = simulate_many(self.steps.runs, RuntimeAdapter(PolicyRuntime(policy, meta)))
        return any(bool(run.diverged.any()) for run in runs)


@dataclass(frozen=True)
class AdaptJob:
    """Everything an adaptation needs, checked (:func:`prepare`); nothing written yet."""

    request: AdaptRequest
    new: NewPlant  #: the plant, on the policy's new row (or a free one, tag-free)
    policy: Policy  #: the base policy, as loaded
    meta: dict[str, Any]
    windows: Windows
    demos: dict[str, Any]  #: where the windows came from, how many
    dagger: tuple[RolloutSampler, ExpertLabeller] | None  #: None: no DAgger round
    score: LoopScore  #: picks the row kept
    base_sha256: str  #: the base policy file's hash: how its training run is found


def _free_row(policy: Policy, meta: dict[str, Any], new: NewPlant) -> int:
    """A normaliser row no trained plant holds (tag-free): its file's tag if free."""
    taken = {int(t) for t in meta["tags"].values()}
    free = [t for t in range(policy.net.n_tags) if t not in taken]
    if not free:
        raise RecipeError(
            f"every one of the tag-free policy's {policy.net.n_tags} normaliser rows is a "
            "trained plant's: none is free for the new plant's scales; retrain it with a "
            "larger model.plant.n_tags"
        )
    return new.file_tag if new.file_tag in free else free[0]


def _windows(request: AdaptRequest, new: NewPlant, policy: Policy) -> tuple[Windows, dict]:
    """The plant's windows: recorded (``demos=``) or generated from its LQI expert."""
    history, horizon, channels = policy.history, policy.horizon, policy.channels
    if request.demos is None:
        return generated_windows(new.plant, request.data, history, horizon, channels)
    controls = "previous_control" in channels
    rec = read_recorded(request.demos, new.plant, new.plant.tag, history, horizon, controls)
    facts = {"source": request.demos, "expert": "recorded", "trajectories": rec.trajectories,
             "windows": len(rec.windows)}  # fmt: skip
    return rec.windows, facts


def _dagger(request: AdaptRequest, new: NewPlant, policy: Policy) -> tuple | None:
    """The training's sampler (on the new plant alone) and labeller; None without rounds."""
    spec = request.dagger
    if spec is None or request.demos is not None or not request.adapt.rounds:
        return None  # a recorded controller cannot label the states the policy visits
    sampler = RolloutSampler([new.plant], spec.sampler, rollout_data(request.data), request.seed)
    return sampler, ExpertLabeller(spec.labeller, policy.history, policy.horizon, policy.channels)


def prepare(request: AdaptRequest) -> AdaptJob:
    """Load the policy, the plant and its windows and check them together; nothing written.

    Raises
    ------
    ValueError
        Naming the fix: a policy that cannot take a row, a plant refused, unusable recorded
        demonstrations, an ``adapt.unfreeze`` name the policy lacks.
    """
    torch.set_num_threads(request.threads)
    if request.policy.startswith(("runs:/", "models:/")):  # the store is touched for these only
        mlflow_utils.set_tracking(request.logger)
    path = resolve(request.policy)
    policy, meta = load_policy(path)
    named_only = not policy.net.plant.reads_tag and not request.adapt.learn
    if not named_only:
        check_growable(policy, request.policy)
    new = load_new_plant(request.plant, meta)
    new = new.on_row(_free_row(policy, meta, new) if named_only else policy.net.n_tags)
    learned_parameters(policy, request.adapt.unfreeze)  # the names checked before any work
    windows, demos = _windows(request, new, policy)
    dagger = None if named_only else _dagger(request, new, policy)
    return AdaptJob(request, new, policy, meta, windows, demos, dagger,
                    LoopScore(new.plant, request.scoring), policy_sha256(path))  # fmt: skip


def _start(job: AdaptJob, tensors: dict[str, torch.Tensor]) -> tuple[Policy, dict[str, Any]]:
    """The grown policy, its new row at its start (``adapt.init``), and how it was chosen."""
    scales = plant_scales(tensors["state"], tensors["mask"], tensors["ref"], tensors["target"])
    if not job.policy.net.plant.reads_tag:  # tag-free: named on a free row, nothing learned
        named = with_scales(job.policy, job.new.plant.tag, scales)
        return named, {"mode": "none", "chosen": None}
    tags = {str(k): int(v) for k, v in job.meta["tags"].items()}
    rows = job.policy.state_dict()[ROWS]
    candidates = {**start_rows(job.policy, tags.values()), **{n: rows[t] for n, t in tags.items()}}
    grown = grow_policy(job.policy, candidates["mean"], scales)
    chosen, losses = "mean", dict[str, float]()
    if job.request.adapt.init == "nearest":
        chosen, losses = nearest_row(grown, job.new.plant.tag, tensors, candidates)
        set_row(grown, job.new.plant.tag, candidates[chosen])
    return grown, {"mode": job.request.adapt.init, "chosen": chosen, "losses": losses}


def _meta(job: AdaptJob, record: dict[str, Any]) -> dict[str, Any]:
    """The adapted policy's meta: the plant added, with what it was adapted from."""
    base = {
        "source": redact(job.request.policy),
        "sha256": job.base_sha256,
        "n_tags": job.policy.net.n_tags,
    }
    keep = ("tag", "file_tag", "demonstrations", "learned")
    facts = {"base": base, "init": record["init"]["chosen"], **{k: record[k] for k in keep}}
    return plant_meta(job.meta, job.new.plant, facts)


def _fit(
    job: AdaptJob, policy: Policy, meta: dict[str, Any], data: WindowTensors, start: float
) -> dict[str, Any]:
    """The fit, then each DAgger round and fit; the lowest-scoring state (later on a tie) kept."""
    s, tag = job.request.adapt, job.new.plant.tag
    learned = learned_parameters(policy, s.unfreeze)
    best, kept, keep = start, "start", copy.deepcopy(policy.state_dict())
    scores, losses, added = [], [], 0
    for i in range(1 + (s.rounds if job.dagger else 0)):
        if i:  # DAgger round i: roll out, label, add, fit again
            sampler, labeller = job.dagger  # type: ignore[misc]
            runtime = PolicyRuntime(policy, meta)
            windows, _ = dagger_round(sampler, labeller, runtime, data, i - 1, s.beta_at(i - 1))
            added += len(windows)
        losses += fit_row(policy, tag, data.tensors, s, learned, job.request.seed + i)
        scores.append(job.score(policy, meta))
        if scores[-1] <= best:
            best, kept = scores[-1], f"round {i}" if i else "fit"
            keep = copy.deepcopy(policy.state_dict())
    policy.load_state_dict(keep)
    loop = {
        "start": start,
        "fit": scores[0],
        "rounds": scores[1:],
        "kept": best,
        "kept_from": kept,
    }
    return {"closed_loop": loop, "loss": losses, "dagger_windows": added}


def learn(job: AdaptJob) -> tuple[Policy, dict[str, Any], dict[str, Any]]:
    """The adapted policy, its meta, and the adaptation's record (scores, losses, windows)."""
    data = WindowTensors(job.windows)
    plant, tag = job.new.plant, job.new.plant.tag
    policy, init = _start(job, data.tensors)
    learning = job.request.adapt.learn and policy.net.plant.reads_tag
    record: dict[str, Any] = {
        "plant": plant.name, "tag": tag, "file_tag": job.new.file_tag,
        "plant_file": str(job.new.path), "demonstrations": dict(job.demos),
        "learned": [f"{ROWS}[{tag}]", *job.request.adapt.unfreeze] if learning else [],
        "init": init,
    }  # fmt: skip
    meta = _meta(job, record)
    start = job.score(policy, meta)
    record["closed_loop"] = {"start": start, "kept": start, "kept_from": "start"}
    if learning:
        fitted = _fit(job, policy, meta, data, start)
        record.update(closed_loop=fitted["closed_loop"], loss=fitted["loss"])
        record["demonstrations"]["dagger_windows"] = fitted["dagger_windows"]
    if job.request.demos is not None and policy.net.plant.reads_tag:
        u, _ = policy.predict_windows(job.windows)  # the recorded controller: the baseline
        target = np.asarray(job.windows.target, dtype=np.float64)
        err = float(np.mean((u - target) ** 2) / max(float(np.mean(target**2)), 1e-300))
        record["recorded_relative_mse"] = err
    return policy, _meta(job, record), record
