"""What the gateway tells on ``<prefix>/<gw>/dev/<device>/event`` and ``<prefix>/<gw>/events``,
as pydantic models: one per event type, told apart by ``type``.

Rules of this file: the rules of ``api`` hold here (what the gateway publishes is described,
not built, and checked against real ones by ``tests/test_schema_export.py``); events are open
(``OpenPublished``): an event type may gain a field without breaking a client that validates
against an older schema.
"""

from __future__ import annotations

import warnings
from typing import Annotated, Literal

from pydantic import Field, TypeAdapter

from busgate.schemas.api import ErrorCode
from busgate.schemas.base import ClientId, OpenPublished


class Event(OpenPublished):
    """Every event's envelope; ``device`` is ``"*"`` for what concerns the whole gateway."""

    ts: float = Field(description="Wall-clock time, Unix seconds.")
    device: str
    type: str


class OnlineEvent(Event):
    type: Literal["online"]


#: An ``offline`` event's reason when the device's bus went down (its port or interface lost).
BUS_DOWN_REASON = "bus down"
#: How an ``offline`` event's reason begins when the worker process running the device's bus
#: ended (killed, crashed, hung); how it ended follows in brackets.
WORKER_ENDED_REASON = "its worker ended"


class OfflineEvent(Event):
    type: Literal["offline"]
    reason: str = Field(
        description=f"Why: no reply, {BUS_DOWN_REASON!r}, heartbeats stopped, "
        f"{WORKER_ENDED_REASON!r} (how) …"
    )


class FaultEvent(Event):
    """The set of faults changed (names as in the kind's telemetry)."""

    type: Literal["fault"]
    faults: list[str]
    raised: list[str]
    cleared: list[str]


class IdChangedEvent(Event):
    type: Literal["id_changed"]
    old_id: int
    new_id: int


# ``register`` shadows ``BaseModel.register`` (ABCMeta's hook): pydantic warns, and without an
# explicit ``Field(...)`` it takes that method for the field's default, making it optional.
with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message='Field name "register"', category=UserWarning)

    class RejectedEvent(Event):
        """The device refused a write (ZLAC706 on CAN: no such register)."""

        type: Literal["rejected"]
        register: int = Field(...)
        reason: str


class StreamStaleEvent(Event):
    """The follow stream got no new target in time: the gateway stopped streaming."""

    type: Literal["stream_stale"]


class StreamStoppedEvent(Event):
    type: Literal["stream_stopped"]
    reason: str


class RebootedEvent(Event):
    """The device powered up again under the gateway (seen in its replies or heartbeats):
    its follow stream was dropped and its settings are written again; nothing moves it until
    a fresh command."""

    type: Literal["rebooted"]
    evidence: str = Field(description="What showed it, e.g. the position counter back at 0.")
    restoring: int = Field(description="How many setting writes are sent again.")


class ClaimedEvent(Event):
    type: Literal["claimed"]
    client: ClientId
    ttl_s: float


class ReleasedEvent(Event):
    type: Literal["released"]
    client: ClientId


class StoppedEvent(Event):
    """The gateway stopped the device on a client's behalf (deadman: the client is gone)."""

    type: Literal["stopped"]
    client: ClientId
    reason: str


class EstopEvent(Event):
    """An e-stop was put (``device`` is ``"*"``): at most one told every 0.1 s, the rest
    counted in the next one's ``suppressed``."""

    type: Literal["estop"]
    key: str = Field(description="The key expression the e-stop was put on.")
    client: ClientId | None = None
    suppressed: int | None = Field(
        default=None,
        description="How many e-stops were not told before this one: at most one is told "
        "every 0.1 s, the rest counted here.",
    )


class EstopResetEvent(Event):
    """The gateway's e-stop was reset: on one device (``device`` names it) or on every one
    (``device`` is ``"*"``, from ``<prefix>/<gw>/estop/reset``: at most one of those told
    every 0.1 s, the rest counted in the next one's ``suppressed``)."""

    type: Literal["estop_reset"]
    client: ClientId | None = None
    suppressed: int | None = Field(
        default=None,
        description="How many resets of every device were not told before this one: at most "
        "one is told every 0.1 s, the rest counted here.",
    )
    not_reset: list[str] | None = Field(
        default=None,
        description="The devices a reset of every device left e-stopped: claimed by another "
        "client than the one it names, theirs to reset.",
    )


class TrajectoryStartedEvent(Event):
    """A trajectory was accepted (``<prefix>/<gw>/trajectory``); ``device`` is ``"*"``."""

    type: Literal["trajectory_started"]
    id: str
    client: ClientId | None = None
    start_at: float = Field(description="When its t_s is 0, Unix seconds.")
    end_at: float = Field(description="When its last point is due, Unix seconds.")


class TrajectoryEndedEvent(Event):
    """A trajectory's result (also on ``<prefix>/<gw>/trajectory/<id>/feedback``)."""

    type: Literal["trajectory_ended"]
    id: str
    client: ClientId | None = None
    result: Literal["succeeded", "canceled", "replaced", "aborted"]
    reason: str | None = Field(default=None, description="Why it was aborted.")
    errors: dict[str, float | None] = Field(
        default_factory=dict,
        description="Each device's final error, raw units (measured minus the path; null: not "
        "read), as its feedback's result gives it.",
    )


class CommandRefusedEvent(Event):
    """A command put (no reply possible) was refused: the error as a reply would carry it."""

    type: Literal["command_refused"]
    code: ErrorCode
    message: str
    suppressed: int | None = Field(
        default=None,
        description="How many refused puts of this device were not told before this one: at "
        "most one is told every 0.1 s a device, the rest counted here.",
    )


class LimitedEvent(Event):
    """A follow stream's target was first held within its joint's limits (clamped to a
    position limit, or its step bounded by ``max_velocity`` or ``max_acceleration``); told
    once per stream."""

    type: Literal["limited"]
    joint: str = Field(description="The joint's name.")
    limit: Literal["min", "max", "max_velocity", "max_acceleration"]
    value: float = Field(description="What the client asked for, in the joint's units.")


class BaseStoppedEvent(Event):
    """A base's wheel left its play (offline, stopped with its bus, refused, or its play
    ended): both wheels were ramped to 0 at once (a base never drives on one wheel);
    ``device`` is the base."""

    type: Literal["base_stopped"]
    base: str = Field(description="The base's name.")
    wheel: str = Field(description="The wheel that left the play.")
    reason: str


KnownEvent = Annotated[
    OnlineEvent | OfflineEvent | FaultEvent | IdChangedEvent | RejectedEvent | StreamStaleEvent
    | StreamStoppedEvent | RebootedEvent | ClaimedEvent | ReleasedEvent | StoppedEvent
    | EstopEvent | EstopResetEvent | TrajectoryStartedEvent | TrajectoryEndedEvent
    | CommandRefusedEvent | LimitedEvent | BaseStoppedEvent,
    Field(discriminator="type"),
]  # fmt: skip
EVENT_ADAPTER: TypeAdapter[KnownEvent] = TypeAdapter(KnownEvent)
