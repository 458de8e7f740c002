"""What every device's telemetry carries, and the naming of its faults.

Each family's schema module defines its ``Telemetry`` on ``TelemetryEnvelope`` (the registry
collects them into the API's telemetry union); fault names come from the codecs' flag enums
through ``flag_names``, the one spelling the drivers publish and the schemas accept.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable
from typing import Annotated, Any, Literal, TypeAlias

from pydantic import Field

from busgate.schemas.base import FINITE, ReadByKey
from busgate.schemas.config import Name
from busgate.schemas.families import kinds
from busgate.schemas.joints import JointState

DeviceKind: TypeAlias = Literal[kinds()]  # type: ignore[valid-type]


def flag_names(flags: Iterable[enum.Flag]) -> list[str]:
    """Flag names as the drivers publish them, in bit order: ``OVER_CURRENT`` → ``over_current``.

    >>> class Fault(enum.Flag):
    ...     STALL = 1
    ...     OVER_CURRENT = 2
    >>> flag_names(Fault.STALL | Fault.OVER_CURRENT)
    ['stall', 'over_current']
    """
    return [flag.name.lower() for flag in flags if flag.name]


def fault_literal(flags: Iterable[enum.Flag]) -> Any:
    """The ``Literal`` type of these flags' names, for a telemetry model's ``faults``."""
    return Literal[tuple(flag_names(flags))]


class TelemetryEnvelope(ReadByKey):
    """The fields every device's state carries, whatever its kind. ``None`` in a value: not
    known yet (never read, or not reported by this device's protocol)."""

    model_config = FINITE

    ts: float = Field(
        description="When the values were read: the wall-clock time (Unix seconds) of the "
        "device's last reply or heartbeat, the same in every state of one reading; for a device "
        "never read, when the state was taken (last_reply_age_s is null)."
    )
    device: Name
    kind: DeviceKind
    online: bool = Field(description="The device answered recently (or sent heartbeats).")
    last_reply_age_s: Annotated[float, Field(ge=0)] | None = Field(
        description="Seconds since the device last answered; null if it never did."
    )
    stale: bool = Field(
        description="The values are older than a few poll periods (an oversubscribed bus, or "
        "a device not answering)."
    )
    estopped: bool = Field(
        description="The gateway e-stopped the device (a put on <prefix>/<gw>/estop, the "
        "safe stop at shutdown, or an Inspire LA's own estop op): motion is refused (estopped) "
        'until its re-enable command, {"op": "enable"} for an Inspire LA or a ZLAC706, '
        '{"op": "torque", "on": true} for a DS servo.'
    )
    joint: JointState = Field(
        description="The device as a joint, in SI units (docs/joints.md), from this reading."
    )
    enabled: bool | None = Field(
        description="The power stage drives the motor; null when not known. Inspire LA: as "
        "commanded (its power is on; paused and estopped are not driving); DS servo: torque "
        "on; ZLAC706: enabled as acknowledged."
    )
