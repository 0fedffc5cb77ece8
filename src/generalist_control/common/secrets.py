"""Credentials never leave the process: one redaction for every URL that is logged or stored.

Tracking URIs and Optuna storage URLs may carry a password (``scheme://user:secret@host``
or ``?password=secret``). :func:`redact` hides it in a string, or in every string of a
(nested) config, before the value is logged, written to a file or sent to MLflow.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

__all__ = ["MASK", "redact"]

#: What a password is replaced with (as SQLAlchemy renders a hidden password).
MASK = "***"

_USERINFO = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.\-]*://[^:/@\s]*):(?P<secret>[^@\s/]*)@")
_QUERY = re.compile(
    r"(?P<head>[?&](?:password|passwd|pwd|token|secret)=)(?P<secret>[^&\s]*)", re.I
)


def redact(value: Any) -> Any:
    """``value`` with passwords in URLs masked; mappings and lists are walked.

    Examples
    --------
    >>> redact("postgresql+psycopg2://gc:hunter2@db:5432/optuna")
    'postgresql+psycopg2://gc:***@db:5432/optuna'
    >>> redact({"uri": "http://u:p@host/?token=abc&x=1"})
    {'uri': 'http://u:***@host/?token=***&x=1'}
    """
    if isinstance(value, str):
        value = _USERINFO.sub(lambda m: f"{m['head']}:{MASK}@", value)
        return _QUERY.sub(lambda m: f"{m['head']}{MASK}", value)
    if isinstance(value, Mapping):
        return {k: redact(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(redact(v) for v in value)
    return value
