"""The checks a key and a name pass before a client's session uses them (zenoh's own parser,
without a session); the keys themselves are ``schemas.keys.Keys``, the API's one spelling of
them, which the gateway declares by too.

>>> keys = Keys("busgate")
>>> keys.device("gw1", "la1", "cmd"), keys.estop("*")
('busgate/gw1/dev/la1/cmd', 'busgate/*/estop')
>>> split_name("gw1/la1"), split_name("la1")
(('gw1', 'la1'), (None, 'la1'))
"""

from __future__ import annotations

import zenoh

from busgate.errors import CommandError
from busgate.schemas.base import NAME_FORM
from busgate.schemas.keys import Keys, is_name
from busgate.schemas.zenoh_session import zenoh_reason

#: zenoh carries a message in batches of 64 KiB; a longer key makes the client session panic.
MAX_KEY_BYTES = 60 * 1024


def check_name(what: str, name: str) -> str:
    """``name`` when it is one chunk of a key as the config allows names; else ``CommandError``
    (a ``*`` or ``/`` in a device name would address others than meant)."""
    if not isinstance(name, str):
        raise CommandError(
            f"not a {what} name: {str(name)[:80]} is a {type(name).__name__}, not a string"
        )
    if not is_name(name):
        raise CommandError(f"not a {what} name: {name[:80]!r} ({NAME_FORM})")
    return name


def split_name(name: str, what: str = "device or bus") -> tuple[str | None, str]:
    """``"gw1/la1"`` → ``("gw1", "la1")``; a bare ``"la1"`` names no gateway. ``what`` the
    leaf names, for the error of one that is not a name."""
    if not isinstance(name, str):
        raise CommandError(f"a name is a string, not {type(name).__name__}")
    gateway, _, leaf = name.rpartition("/")
    if not gateway:
        return None, check_name(what, leaf)
    return check_name("gateway", gateway), check_name(what, leaf)


def check_key(text: str) -> str:
    """``text`` when zenoh takes it as a key expression; ``CommandError`` (one line) when zenoh
    would refuse it, or it is too long for a zenoh message (the session would panic)."""
    if not isinstance(text, str):
        raise CommandError(f"a key expression is text, not {type(text).__name__}")
    size = len(text.encode())
    if size > MAX_KEY_BYTES:
        raise CommandError(
            f"a key expression of {size} bytes: at most {MAX_KEY_BYTES} fit in a zenoh message"
        )
    try:
        zenoh.KeyExpr(text)
    except zenoh.ZError as exc:
        raise CommandError(f"not a key expression: {text[:200]!r} ({zenoh_reason(exc)})") from exc
    return text


def intersects(selector: str, key: str) -> bool:
    """Whether the key expression ``selector`` matches ``key`` (both checked already).

    >>> intersects("busgate/gw1/**", "busgate/gw1/dev/la1/state"), intersects("a/*", "b/c")
    (True, False)
    """
    return zenoh.KeyExpr(selector).intersects(zenoh.KeyExpr(key))


__all__ = [
    "MAX_KEY_BYTES",
    "Keys",
    "check_key",
    "check_name",
    "intersects",
    "is_name",
    "split_name",
]
