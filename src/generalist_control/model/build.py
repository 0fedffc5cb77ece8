"""Build the network from its config (``conf/model``, or a policy file's copy) with Hydra.

Only classes of :mod:`generalist_control.model` may be named: loading a policy file calls
nothing else.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate

from generalist_control.model.network import GeneralistNetwork

__all__ = ["TARGET_PREFIX", "build_network", "targets"]

#: Where every ``_target_`` of a network config must live.
TARGET_PREFIX = "generalist_control.model."


def _nodes(config: Any, path: str = "model") -> Iterator[tuple[str, Mapping[str, Any]]]:
    """Every mapping in ``config`` that names a ``_target_``, with its dotted path."""
    if isinstance(config, Mapping):
        if "_target_" in config:
            yield path, config
        for key, value in config.items():
            yield from _nodes(value, f"{path}.{key}")
    elif isinstance(config, list | tuple):
        for i, value in enumerate(config):
            yield from _nodes(value, f"{path}[{i}]")


def targets(config: Any) -> dict[str, str]:
    """Every ``_target_`` in ``config`` by its dotted path (``model``, ``model.plant``, ...)."""
    return {path: str(node["_target_"]) for path, node in _nodes(config)}


def build_network(config: Mapping[str, Any]) -> GeneralistNetwork:
    """The :class:`GeneralistNetwork` that ``config`` (plain types) describes.

    Raises
    ------
    ValueError
        If the config names no network, a class outside :data:`TARGET_PREFIX`, or a value
        a part refuses (the message is the part's own, naming the config key).
    """
    found = targets(config)
    if "model" not in found:
        raise ValueError(
            "the model config names no network (model._target_ is missing): compose it from "
            "conf/model (e.g. model=generalist)"
        )
    outside = {k: v for k, v in found.items() if not v.startswith(TARGET_PREFIX)}
    if outside:
        raise ValueError(
            f"the model config names classes outside {TARGET_PREFIX[:-1]}: {outside}; a network "
            "is built from the project's own parts only"
        )
    partial = [
        p for p, node in _nodes(config) if p != "model" and node.get("_partial_") is not True
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
