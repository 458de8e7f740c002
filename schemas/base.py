"""What every command model shares (strict parsing, the client field, hex data), the names
of things, and the two bases of what the gateway publishes.

Rules: a command is refused, never coerced. Unknown fields, strings for numbers, floats for
integers, NaN and infinities are validation errors, so a malformed command cannot reach a wire.
Ranges come from the codecs' register tables, never retyped here.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

#: A client's self-chosen identity: 1–64 letters, digits, ``_`` or ``-``.
CLIENT_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
#: What ``CLIENT_ID_PATTERN`` takes, as a refusal says it.
NAME_FORM = "1-64 of A-Z a-z 0-9 _ -"
ClientId = Annotated[str, Field(pattern=CLIENT_ID_PATTERN)]
#: A gateway's, bus's, device's or joint's name: names end up in zenoh key expressions, so
#: they are one safe chunk, as a client id is.
Name = Annotated[str, Field(pattern=CLIENT_ID_PATTERN)]
#: The chunk under the prefix where clients hold their liveliness tokens
#: (``<prefix>/clients/<id>``): no gateway's name, or a client named ``alive`` would be taken
#: for a gateway of that name (an audit: the dashboard showed one, with an e-stop button).
CLIENTS_ROOM = "clients"
#: The prefix of every key (``[gateway] prefix``): one to eight such names joined by ``/``,
#: no wildcard.
KEY_PREFIX_PATTERN = r"^[A-Za-z0-9_-]{1,64}(/[A-Za-z0-9_-]{1,64}){0,7}$"
#: What ``KEY_PREFIX_PATTERN`` takes, as a refusal says it.
KEY_PREFIX_FORM = f"one to eight names of {NAME_FORM}, joined by /"


def require_distinct(ids: list[int], what: str) -> None:
    """``ValueError`` (a schema's refusal) when ``ids`` names one id twice: a group frame or a
    scan addresses each device once."""
    if len(set(ids)) != len(ids):
        raise ValueError(f"{what} must be distinct, got {ids}")


def client_named(value: object) -> str | None:
    """``value`` when it is a valid client id (what a payload's ``client`` names), else
    ``None``: for what only reports a client, never trusts it."""
    return value if isinstance(value, str) and re.fullmatch(CLIENT_ID_PATTERN, value) else None


#: Raw bytes written to a device, as hex without spaces (``"e803"``).
HexData = Annotated[str, Field(pattern=r"^(?:[0-9a-fA-F]{2})+$", max_length=512)]


#: The longest claim a client may ask for, in seconds.
MAX_CLAIM_S = 3600.0


class CommandModel(BaseModel):
    """Base of every JSON command: strict, closed, immutable."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    client: ClientId | None = None
    #: A client that claimed sends this, so that nothing it meant to do under its claim is
    #: done without it: refused (``not_claimed``) unless ``client`` holds the claim of every
    #: device the command needs a claim for (reads and stops need none).
    require_claim: bool = False


#: A client's count of what it sends to one device's follow stream (its targets and the
#: ``end_follow`` that ends it), increasing: it orders a target against an end whichever of
#: zenoh's threads each reached the gateway on.
FollowSeq = Annotated[int, Field(ge=0, le=2**63 - 1)]


class FollowModel(CommandModel):
    """Base of what a follow key takes: a target, the client, and the client's ``seq``."""

    seq: FollowSeq | None = None


class Published(BaseModel):
    """Base of what the gateway publishes and clients only read: closed, no coercion."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


#: What a published model whose numbers are never NaN or infinite adds to its base's config
#: (``model_config = FINITE``): the gateway computes them finite and its encoder would write
#: a non-finite one ``null`` (``schemas.encoding``), so one in a message is a peer's, refused.
FINITE = ConfigDict(allow_inf_nan=False)


class ReadByKey(Published):
    """Published data that can also be read as the JSON object it came as: ``info["buses"]``
    is ``info.buses``, and ``get``, ``in``, ``keys``, ``values`` and ``items`` answer as a
    dict's would (so ``dict(info)`` is its fields). Kept for scripts written against the
    earlier release, whose ``Client.gateways()`` returned the raw reply; new code reads
    attributes (a device's state too: ``device["state"]["position"]`` is
    ``device.state.position``). Reads only: iterating gives pydantic's ``(field, value)``
    pairs, ``==`` compares models, and ``model_dump(mode="json")`` gives the object itself
    (``json.dumps`` takes that, not the model)."""

    def __getitem__(self, key: str) -> Any:
        if key in type(self).model_fields:
            return getattr(self, key)
        raise KeyError(key)

    def get(self, key: str, default: Any = None) -> Any:
        try:
            return self[key]
        except KeyError:
            return default

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and key in type(self).model_fields

    def keys(self) -> list[str]:
        return list(type(self).model_fields)

    def values(self) -> list[Any]:
        return [getattr(self, key) for key in type(self).model_fields]

    def items(self) -> list[tuple[str, Any]]:
        return [(key, getattr(self, key)) for key in type(self).model_fields]


class OpenPublished(BaseModel):
    """Base of published data that may gain fields: ok replies, events."""

    model_config = ConfigDict(extra="allow", strict=True, frozen=True)
