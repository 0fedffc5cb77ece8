"""Plain containers from OmegaConf nodes, typed for the code that reads them."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

__all__ = ["as_dict", "as_list"]


def as_dict(node: Any) -> dict[str, Any]:
    """``node`` (a config mapping, or a plain mapping) resolved into a plain ``dict``.

    Raises
    ------
    TypeError
        If ``node`` is not a mapping.
    """
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, dict):
        raise TypeError(f"expected a config mapping, got {type(node).__name__}: {node!r}")
    return node


def as_list(node: Any) -> list[Any]:
    """``node`` (a config list, or a plain sequence) resolved into a plain ``list``."""
    if isinstance(node, ListConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, list | tuple):
        raise TypeError(f"expected a config list, got {type(node).__name__}: {node!r}")
    return list(node)
