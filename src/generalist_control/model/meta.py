"""What a policy file says of its plants, checked against its network before it is used."""

from __future__ import annotations

import math
import numbers
from typing import Any, cast

from generalist_control.model.network import GeneralistNetwork

__all__ = ["check_meta"]


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
