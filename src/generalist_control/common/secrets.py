"""Credentials never leave the process: one redaction for every URL that is logged or stored.

Masked: a password in a URL's userinfo (any characters, with or without a scheme), a token
as an http(s) user, and query or fragment parameters named by a secret word (``?token=``),
also in Hydra's escaped rendering of an override (a backslash before ``:`` and ``=``).
"""

from __future__ import annotations

import re
import traceback
from collections.abc import Mapping
from typing import Any

__all__ = ["MASK", "RedactedError", "redact", "redact_exception"]

#: What a password is replaced with (as SQLAlchemy renders a hidden password).
MASK = "***"

# The password runs to the last "@" of its token, never across whitespace, a quote or "://".
_PASSWORD = r"(?P<sep>\\*:)(?P<secret>(?:(?!\\*://)[^\s'\"])*)@"
_USERINFO = (
    re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.\-]*\\*://[^\s:/@'\"\\]*)" + _PASSWORD),
    # without a scheme: user:secret@host, not scheme://user@host
    re.compile(r"(?<![\w.%+\-/:\\@*])(?P<head>[\w.%+\-]+)(?!\\*://)" + _PASSWORD),
)
#: A user alone in an http(s) URL is how tokens travel (``https://<token>@host``): masked too.
_HTTP_USER = re.compile(r"(?P<head>https?\\*://)(?P<user>[^\s:/@'\"\\]+)@", re.I)
#: A query or fragment parameter whose name ends in a secret word (``access_token``, ``sas``).
_SECRET_WORDS = (
    r"pass|passwd|password|passphrase|pwd|token|secret|key|sig|signature|credentials?|auth\w*"
    r"|sas|jwt|code|pat|bearer|session\w*|cookie"
)
_QUERY = re.compile(
    rf"(?P<head>[?&;#][\w.\-]*?(?:{_SECRET_WORDS})s?\\*=)(?P<secret>(?:\\.|[^&;#\s'\"\]\\])*)",
    re.I,
)


def redact(value: Any) -> Any:
    """``value`` with credentials in URLs masked; mappings and lists are walked.

    Examples
    --------
    >>> redact({"uri": "http://u:p@host/?token=abc&x=1"})
    {'uri': 'http://u:***@host/?token=***&x=1'}
    >>> redact("https://ghp_abc123@github.com/org/repo.git")
    'https://***@github.com/org/repo.git'
    """
    if isinstance(value, str):
        for pattern in _USERINFO:
            value = pattern.sub(rf"\g<head>\g<sep>{MASK}@", value)
        value = _HTTP_USER.sub(rf"\g<head>{MASK}@", value)
        return _QUERY.sub(lambda m: f"{m['head']}{MASK}", value)
    if isinstance(value, Mapping):
        return {k: redact(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(redact(v) for v in value)
    return value


class RedactedError(RuntimeError):
    """An error whose text held a credential, masked: its chain's messages, the traceback kept."""


def _chain(ex: BaseException) -> list[BaseException]:
    """``ex`` and the errors it was raised from or during, as a traceback would print them."""
    out: list[BaseException] = []
    cur: BaseException | None = ex
    while cur is not None and all(cur is not e for e in out):
        out.append(cur)
        cur = cur.__cause__ or (None if cur.__suppress_context__ else cur.__context__)
    return out


def redact_exception(ex: BaseException) -> BaseException:
    """``ex`` itself if none of its chain's text holds a credential, else a :class:`RedactedError`.

    Its message is each error's type and message (``caused by ...``), redacted.
    """
    texts = ["".join(traceback.format_exception_only(type(e), e)).strip() for e in _chain(ex)]
    if all(redact(t) == t for t in texts):
        return ex
    message = "\n".join([redact(texts[0]), *(f"  caused by {redact(t)}" for t in texts[1:])])
    clean = RedactedError(message).with_traceback(ex.__traceback__)
    clean.__suppress_context__ = True
    return clean
