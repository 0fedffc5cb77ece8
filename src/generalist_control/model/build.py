"""Build the network from its config (``conf/model``, or the copy a policy file stores).

The config is Hydra's: the network and each part name their class with ``_target_``. A part
is built by what holds it, which gives it its sizes, so every nested ``_target_`` is made
``_partial_`` here (:func:`as_parts`); the config files need not say so. A policy file
stores the resolved config as plain types, so loading one rebuilds the same network. Only
classes of :mod:`generalist_control.model` may be named: a policy file cannot make the
loader call anything else.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate

from generalist_control.model.network import GeneralistNetwork

__all__ = ["TARGET_PREFIX", "as_parts", "build_network", "targets"]

#: Where every ``_target_`` of a network config must live.
TARGET_PREFIX = "generalist_control.model."


def targets(config: Any, path: str = "model") -> dict[str, str]:
    """Every ``_target_`` in ``config`` by its dotted path (``model``, ``model.plant``, ...)."""
    found: dict[str, str] = {}
    if isinstance(config, Mapping):
        if "_target_" in config:
            found[path] = str(config["_target_"])
        for key, value in config.items():
            found.update(targets(value, f"{path}.{key}"))
    elif isinstance(config, list | tuple):
        for i, value in enumerate(config):
            found.update(targets(value, f"{path}[{i}]"))
    return found


def as_parts(config: Any, root: bool = True) -> Any:
    """``config`` with every nested node that names a ``_target_`` marked ``_partial_``."""
    if isinstance(config, Mapping):
        out = {k: as_parts(v, root=False) for k, v in config.items()}
        if "_target_" in out and not root:
            out["_partial_"] = True
        return out
    if isinstance(config, list | tuple):
        return [as_parts(v, root=False) for v in config]
    return config


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
    try:
        net = instantiate(as_parts(dict(config)), _convert_="all")
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, ValueError | TypeError):
            raise ValueError(str(cause)) from exc
        raise ValueError(f"the model config could not be built: {exc}") from exc
    if not isinstance(net, GeneralistNetwork):
        raise ValueError(f"model._target_ must build a GeneralistNetwork, got {found['model']}")
    return net
