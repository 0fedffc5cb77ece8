"""Plain containers from OmegaConf nodes, typed for the code that reads them."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

__all__ = ["as_dict"]


def as_dict(node: Any) -> dict[str, Any]:
    """``node`` (a config or plain mapping) resolved into a plain ``dict``; else a TypeError."""
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, dict):
        raise TypeError(f"expected a config mapping, got {type(node).__name__}: {node!r}")
    return node
