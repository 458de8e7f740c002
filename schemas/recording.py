"""What only a recording holds: the frames on a bus and the commands the gateway was sent, as
the daemon's flight recorder writes them into an incident file (``<prefix>/<gw>/bus/<bus>/frames``
and ``<prefix>/<gw>/commands``, channels no gateway publishes on).

Rules: like everything the gateway writes, these are described here and built elsewhere
(``busgate.gateway.recording.flight``); ``tests/test_schema_export.py`` checks real ones.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from busgate.schemas.api import ErrorCode
from busgate.schemas.base import ClientId, Published
from busgate.schemas.config import Name


class RecordedFrame(Published):
    """One frame, or one read of bytes, on a bus, as the gateway's host saw it."""

    ts: float = Field(
        description="Wall-clock time, Unix seconds: when the write returned, or when the "
        "read bytes arrived."
    )
    bus: Name
    dir: Literal["tx", "rx"] = Field(description="tx: sent by the gateway; rx: received by it.")
    wire: str = Field(
        description="The bytes as hex (a UART: one write, or what one read returned, which "
        "may hold part of a frame or several); on CAN one frame, as cansend writes it: "
        "<3 hex digit id>#<data hex>."
    )


class RecordedCommand(Published):
    """A command the gateway was sent, and how it answered."""

    ts: float = Field(description="Wall-clock time of the answer, Unix seconds.")
    key: str = Field(description="The key expression the command came on.")
    client: ClientId | None = Field(description="The client the command names, if any.")
    command: dict[str, Any] | None = Field(
        description="The payload, when it was a JSON object (else null: see text)."
    )
    text: str | None = Field(
        description="The payload as text (its first 256 characters), when it was no JSON object."
    )
    code: Literal["ok"] | ErrorCode = Field(
        description="ok, or the error code the gateway answered with."
    )
