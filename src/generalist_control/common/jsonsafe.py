"""Strict JSON, written atomically: non-finite numbers become ``null``.

DVC's metrics reader, MLflow and most parsers reject ``NaN``/``Infinity``, so a diverged
score is written as ``null``; every JSON file the project writes goes through :func:`write_json`.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["finite", "strict", "write_json", "write_text_atomic"]


def finite(value: Any) -> float | None:
    """``value`` as a finite float, or None (not a number, NaN or infinite)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def strict(obj: Any) -> Any:
    """``obj`` with every non-finite float (numpy's included) replaced by ``None``.

    Examples
    --------
    >>> strict({"a": float("nan"), "b": [1.0, float("inf")], "c": "x"})
    {'a': None, 'b': [1.0, None], 'c': 'x'}
    """
    if isinstance(obj, Mapping):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict(v) for v in obj]
    if isinstance(obj, float) or type(obj).__module__ == "numpy" and hasattr(obj, "item"):
        value = obj.item() if hasattr(obj, "item") else obj
        if isinstance(value, float) and not math.isfinite(value):
            return None
        return value
    return obj


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary sibling and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | Path, data: Any, indent: int = 2, sort_keys: bool = False) -> Path:
    """Write ``data`` as strict JSON (see :func:`strict`), atomically."""
    text = json.dumps(strict(data), indent=indent, sort_keys=sort_keys, allow_nan=False)
    return write_text_atomic(path, text + "\n")
