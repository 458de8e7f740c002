"""Whom an e-stop's or its reset's payload names: the e-stop takes any payload (a panic
button's is whatever it sends) and names its sender for the log alone; the reset takes an
empty or blank one, or an object holding nothing but a ``client`` that is a client id (or
null), and any other is refused, nothing reset (docs/api.md, the e-stop and its reset)."""

from __future__ import annotations

import json

from busgate.errors import RefusedError
from busgate.schemas.base import client_named
from busgate.schemas.payload import decode_object
from busgate.schemas.validation import shown


def estop_sender(payload: bytes) -> str | None:
    """The client an e-stop payload names (``{"client": "teleop"}``), if it names one validly:
    for the log only, the e-stop itself takes any payload."""
    try:
        return _named_sender(payload)
    except RefusedError:
        return None


def reset_sender(payload: bytes) -> str | None:
    """The client a reset's payload names (``None``: none); ``RefusedError`` for one the reset
    does not take: a command put on the reset's key by mistake resets nothing."""
    return _named_sender(payload, only_client=True)


def _named_sender(payload: bytes, *, only_client: bool = False) -> str | None:
    """The client a payload of the e-stop's or its reset's names (``None``: empty or blank,
    or naming none); ``RefusedError`` for a payload that is no JSON object, or a ``client``
    that is no client id, or (``only_client``: a reset's) that holds anything else: a
    command put on the reset's key by mistake resets nothing."""
    if not payload.strip():
        return None
    fields = decode_object(payload)
    if only_client and (others := sorted(set(fields) - {"client"})):
        raise RefusedError(
            "bad_command",
            f'a reset of every device takes nothing but "client", not '
            f"{shown(', '.join(others))}: nothing was reset",
        )
    client = fields.get("client")
    sender = client_named(client)
    if client is not None and sender is None:
        named = f"'{shown(client)}'" if isinstance(client, str) else json.dumps(client)[:40]
        raise RefusedError("bad_command", f"client {named} is no client id")
    return sender
