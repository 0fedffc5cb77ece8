"""The deployable policy (normaliser + network built from its config), its file, its flat view.

:class:`Policy` is the one preprocessing path: training, evaluation and deployment all call it.
A policy file holds plain types and tensors only (``torch.load(..., weights_only=True)``):
``format_version``, ``model`` (the network's config), ``state_dict`` and ``meta`` (tags, ...).
"""

from __future__ import annotations

import hashlib
import math
import numbers
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from torch import Tensor, nn
from torch.func import functional_call

from generalist_control.data.windows import Windows
from generalist_control.model.network import GeneralistNetwork, NetOutput
from generalist_control.model.normalise import Normaliser

__all__ = [
    "POLICY_FILE",
    "FlatPolicy",
    "POLICY_FORMAT_VERSION",
    "RETRAIN",
    "TARGET_PREFIX",
    "Policy",
    "PolicyFileError",
    "build_network",
    "check_meta",
    "flat_columns",
    "load_policy",
    "policy_sha256",
    "save_policy",
]

#: 3: parts marked ``_partial_`` in the network config (2: marked by the loader).
POLICY_FORMAT_VERSION = 3

#: File name of a policy: ``models/policy.ckpt`` and the MLflow artifact ``policy/policy.ckpt``.
POLICY_FILE = "policy.ckpt"

#: How a policy file is made again.
RETRAIN = "`dvc repro train` (the pipeline's models/policy.ckpt) or `python train.py` (any run)"


#: Where every ``_target_`` of a network config must live: loading a policy file calls nothing
#: else.
TARGET_PREFIX = "generalist_control.model."


class PolicyFileError(ValueError):
    """A file that is not a policy of this project (or of this version): nothing is loaded."""


def _targets(config: Any, path: str = "model") -> Iterator[tuple[str, Mapping[str, Any]]]:
    """Every mapping in ``config`` that names a ``_target_``, with its dotted path."""
    if isinstance(config, Mapping):
        if "_target_" in config:
            yield path, config
        for key, value in config.items():
            yield from _targets(value, f"{path}.{key}")
    elif isinstance(config, list | tuple):
        for i, value in enumerate(config):
            yield from _targets(value, f"{path}[{i}]")


def build_network(config: Mapping[str, Any]) -> GeneralistNetwork:
    """The :class:`GeneralistNetwork` that ``config`` (plain types, ``conf/model``) describes.

    Raises
    ------
    ValueError
        If the config names no network, a class outside :data:`TARGET_PREFIX`, a part not
        marked ``_partial_``, or a value a part refuses (the message is the part's own,
        naming the config key).
    """
    nodes = dict(_targets(config))
    if "model" not in nodes:
        raise ValueError(
            "the model config names no network (model._target_ is missing): compose it from "
            "conf/model (e.g. model=generalist)"
        )
    found = {path: str(node["_target_"]) for path, node in nodes.items()}
    outside = {k: v for k, v in found.items() if not v.startswith(TARGET_PREFIX)}
    if outside:
        raise ValueError(
            f"the model config names classes outside {TARGET_PREFIX[:-1]}: {outside}; a network "
            "is built from the project's own parts only"
        )
    partial = [
        p for p, node in nodes.items() if p != "model" and node.get("_partial_") is not True
    ]
    if partial:
        raise ValueError(
            f"{', '.join(partial)} must be a part the network builds: add `_partial_: true` "
            "beside its _target_ (conf/model/plant/tag.yaml shows how)"
        )
    try:
        net = instantiate(dict(config), _convert_="all")
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, ValueError | TypeError):
            raise ValueError(str(cause)) from exc
        raise ValueError(f"the model config could not be built: {exc}") from exc
    if not isinstance(net, GeneralistNetwork):
        raise ValueError(f"model._target_ must build a GeneralistNetwork, got {found['model']}")
    return net


class Policy(nn.Module):
    """Normaliser and network (``model``: ``conf/model``): raw windows in, plant-unit controls."""

    def __init__(self, model: Mapping[str, Any]) -> None:
        super().__init__()
        self.config: dict[str, Any] = dict(model)
        net = build_network(self.config)
        self.normaliser = Normaliser(net.n_tags, net.width, net.plant.maps_states)
        self.net = net
        self.history: int = net.history  #: samples per window (``T_h``)
        self.horizon: int = net.horizon  #: controls per window (``K``)
        self.width: int = net.width  #: entries per window sample: padded state, channels
        self.channels: tuple[str, ...] = net.channels  #: the window's extra channels

    def network_inputs(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Raw windows as the network's layers see them: normalised, window-scaled; and s."""
        state, mask, ref, tag = self.normaliser.normalise_inputs(state, mask, ref, tag)
        state, ref, s = self.net.scaled_inputs(state, ref)
        return state, mask, ref, tag, s

    def output(self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor) -> NetOutput:
        """The network's output for raw windows (normalised by the plant's tag)."""
        state, mask, ref, tag = self.normaliser.normalise_inputs(state, mask, ref, tag)
        return self.net(state, mask, ref, tag)

    def errors(
        self, batch: Mapping[str, Tensor], params: Mapping[str, Tensor] | None = None
    ) -> tuple[Tensor, NetOutput]:
        """The imitation loss's squared errors (B, horizon) on ``batch``, and the output.

        In normalised units over the window scale; ``params`` replace the network's
        parameters of those names (:func:`torch.func.functional_call`).
        """
        tag = batch["tag"]
        args = self.normaliser.normalise_inputs(batch["state"], batch["mask"], batch["ref"], tag)
        out = self.net(*args) if params is None else functional_call(self.net, dict(params), args)
        target = self.normaliser.normalise_controls(batch["target"], tag)
        return (out.control - target / out.scale) ** 2, out

    def forward(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Controls ``u[k .. k + horizon - 1]`` in plant units (B, horizon) and gates (B, M)."""
        out = self.output(state, mask, ref, tag)
        return self.normaliser.denormalise_controls(out.control * out.scale, tag), out.gates

    @torch.no_grad()
    def predict_windows(
        self, windows: Windows, batch_size: int = 8192
    ) -> tuple[np.ndarray, np.ndarray]:
        """Controls (W, horizon) and gate weights (W, M) for ``windows``, as float32 arrays."""
        self.eval()
        device = next(self.parameters()).device
        us, gs = [], []
        for i in range(0, len(windows), batch_size):
            sl = slice(i, i + batch_size)
            args = [
                torch.as_tensor(np.asarray(a[sl]), device=device)
                for a in (windows.state, windows.mask, windows.ref, windows.tag)
            ]
            u, g = self(*args)
            us.append(u.cpu().numpy())
            gs.append(g.cpu().numpy())
        if not us:
            empty = np.zeros((0, self.horizon), np.float32)
            return empty, np.zeros((0, self.net.n_experts), np.float32)
        return np.concatenate(us), np.concatenate(gs)


def flat_columns(history: int, state_dim: int) -> list[str]:
    """Column names of :class:`FlatPolicy`'s input (``k = 0``: the oldest sample)."""
    cols = [f"state_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"mask_{k}_{i}" for k in range(history) for i in range(state_dim)]
    cols += [f"ref_{k}" for k in range(history)]
    return [*cols, "tag"]


class FlatPolicy(nn.Module):
    """MLflow's one-array view: float32 (B, 2 T width + T + 1) in :func:`flat_columns`."""

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, x: Tensor) -> Tensor:
        """Controls (B, horizon) in plant units for flat rows ``x``."""
        T, n = self.policy.history, self.policy.width
        state = x[:, : T * n].reshape(-1, T, n)
        mask = x[:, T * n : 2 * T * n].reshape(-1, T, n)
        ref = x[:, 2 * T * n : 2 * T * n + T]
        tag = x[:, -1].round().long()
        return self.policy(state, mask, ref, tag)[0]


def save_policy(path: str | Path, policy: Policy, meta: dict[str, Any]) -> Path:
    """Write ``policy`` and plain-typed ``meta`` to ``path`` (atomically: a temporary, renamed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in policy.state_dict().items()}
    blob = {
        "format_version": POLICY_FORMAT_VERSION,
        "model": dict(policy.config),
        "state_dict": state,
        "meta": meta,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def policy_sha256(path: str | Path) -> str:
    """``sha256:<hex>`` of a policy file's bytes: its identity (same weights, same bytes)."""
    return "sha256:" + hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_meta(meta: dict[str, Any], net: GeneralistNetwork) -> None:
    """Refuse meta the network cannot serve: tags, orders, ``dt``, window sizes.

    Raises
    ------
    ValueError
        Naming the first inconsistency: a tag outside ``0 .. n_tags - 1`` or used twice, an
        order outside ``1 .. state_dim``, a plant with a tag but no order, ``dt`` not a
        positive finite number, or a window size other than the network's.
    """
    tags, orders = meta.get("tags"), meta.get("orders")
    if not isinstance(tags, dict) or not tags or not isinstance(orders, dict):
        raise ValueError("its meta lists no plants (tags and orders)")
    n_tags, state_dim = net.n_tags, net.state_dim
    for name, tag in tags.items():
        if not _is_int(tag) or not 0 <= int(tag) < n_tags:
            raise ValueError(f"plant {name!r} has tag {tag!r}, outside 0..{n_tags - 1}")
        order = orders.get(name)
        if not _is_int(order) or not 1 <= int(cast(int, order)) <= state_dim:
            raise ValueError(f"plant {name!r} has order {order!r}, outside 1..{state_dim}")
    if len(set(tags.values())) != len(tags):
        raise ValueError(f"two plants share a tag: {tags}")
    dt = meta.get("dt")
    if (
        not isinstance(dt, numbers.Real)
        or isinstance(dt, bool)
        or not (math.isfinite(float(dt)) and float(dt) > 0)
    ):
        raise ValueError(f"its sample time dt = {dt!r} is not a positive number")
    for key in ("history", "horizon"):
        if meta.get(key) != getattr(net, key):
            raise ValueError(
                f"its meta says {key} = {meta.get(key)!r}, its network {getattr(net, key)}"
            )


def _read(path: Path, map_location: str | torch.device) -> dict[str, Any]:
    """The file's contents, or :class:`PolicyFileError` naming what it is not."""
    if not path.is_file():
        raise PolicyFileError(f"no policy file at {path}; make one with {RETRAIN}")
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # truncated, empty, random bytes, ONNX, pickled code, ...
        raise PolicyFileError(
            f"{path} is not a policy file of this project (torch could not read it as one: "
            f"{type(exc).__name__}); a policy is the policy.ckpt (or a training checkpoint) "
            f"that training writes; make it again with {RETRAIN}"
        ) from None
    if not isinstance(blob, dict):
        raise PolicyFileError(f"{path} holds a {type(blob).__name__}, not a policy; {RETRAIN}")
    return blob


def _parts(path: Path, blob: dict[str, Any]) -> tuple[Any, Any, Any]:
    """The network config, meta and weights of a policy file or a Lightning checkpoint."""
    if "pytorch-lightning_version" in blob:  # a checkpoint of the training module
        hp = blob.get("hyper_parameters", {})
        state = {
            k[len("policy.") :]: v
            for k, v in blob.get("state_dict", {}).items()
            if k.startswith("policy.")
        }
        return hp.get("model"), dict(hp.get("meta", {})), state
    version = blob.get("format_version")
    if version != POLICY_FORMAT_VERSION:
        raise PolicyFileError(
            f"{path}: policy format {version!r}; this code reads format "
            f"{POLICY_FORMAT_VERSION}. Retrain it with this version: {RETRAIN}"
        )
    return blob.get("model"), blob.get("meta"), blob.get("state_dict")


def load_policy(
    path: str | Path, map_location: str | torch.device = "cpu"
) -> tuple[Policy, dict[str, Any]]:
    """Load a policy file or a training (Lightning) checkpoint; return it (eval mode) and its meta.

    ``weights_only=True``: no code is unpickled; the network is built from the project's own
    classes only.

    Raises
    ------
    PolicyFileError
        If the file is missing, unreadable, not a policy, of an older format (a network
        config without ``_target_``), its weights do not fit its config, or its meta is
        inconsistent (unknown tag, order out of range, dt not positive, ...); the message
        names the file and the command that remakes it.
    """
    path = Path(path)
    model, meta, state = _parts(path, _read(path, map_location))
    if not isinstance(model, Mapping) or "_target_" not in model:
        raise PolicyFileError(
            f"{path} was written by an older version of this project (its network config "
            f"has no _target_: a flat list of switches); retrain it: {RETRAIN}"
        )
    try:
        policy = Policy(model)
    except ValueError as exc:
        raise PolicyFileError(
            f"{path}: its network config is refused ({exc}); remake it with {RETRAIN}"
        ) from None
    if not isinstance(state, Mapping) or not isinstance(meta, Mapping):
        raise PolicyFileError(f"{path} has no weights or no meta; {RETRAIN}")
    try:
        policy.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[:3]
        raise PolicyFileError(
            f"{path}: its weights do not fit the network its config describes "
            f"({' '.join(s.strip() for s in first)}); the file was altered or mixed up. "
            f"Remake it with {RETRAIN}"
        ) from None
    try:
        check_meta(dict(meta), policy.net)
    except ValueError as exc:
        raise PolicyFileError(f"{path}: {exc}; remake it with {RETRAIN}") from None
    return policy.eval(), dict(meta)
