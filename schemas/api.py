"""The zenoh API's data, as pydantic models: replies, telemetry, bus statistics, info, and the
gateway-level commands (claims and the end of a follow stream on a device, group moves
and scans on a bus).

Rules of this file:

1. What clients send is validated as strictly as every device command (``CommandModel``:
   closed, no coercion, no NaN). What the gateway publishes is described here, not built
   here: the drivers, the runner and the bridge produce plain dicts, and
   ``tests/test_schema_export.py`` checks real ones against these models and the exported
   JSON Schemas, so the two cannot drift apart unnoticed. The events are ``events``'.
2. Telemetry, bus statistics and info are closed (``extra="forbid"``): every key is named and
   given its unit here, and a key a driver adds without documenting it fails the test. Ok
   replies and events are open: a read adds ``data`` and ``values``, and an event type may
   gain a field without breaking a client that validates against an older schema.
3. Names and units come from the codecs (fault names from their flag enums, ranges from
   their tables), never retyped where a codec already says them.
"""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal, TypeAlias, Union, get_args

from pydantic import BaseModel, Field, TypeAdapter, model_validator

from busgate.schemas.base import (
    FINITE,
    MAX_CLAIM_S,
    ClientId,
    CommandModel,
    FollowModel,
    FollowSeq,
    OpenPublished,
    Published,
    ReadByKey,
    require_distinct,
)
from busgate.schemas.config import Name
from busgate.schemas.families import FAMILIES, PROTOCOLS
from busgate.schemas.joints import MAX_SI, JointType, Unit
from busgate.schemas.telemetry import DeviceKind, TelemetryEnvelope

#: The stable error codes of ``{"ok": false, "error": {"code": …}}``; renaming one breaks clients.
ErrorCode = Literal[
    "not_utf8", "not_json", "too_large", "bad_command", "out_of_range", "unknown_device",
    "unknown_bus", "claimed", "not_claimed", "estopped", "device_timeout", "device_refused",
    "bus_unavailable", "busy", "internal",
]  # fmt: skip
ERROR_CODES: tuple[str, ...] = get_args(ErrorCode)

ProtocolName: TypeAlias = Literal[tuple(PROTOCOLS)]  # type: ignore[valid-type]

#: The most ids one scan may name (every id a one-byte address leaves, bar broadcast).
MAX_SCAN_IDS = 254


# --- gateway-level commands -----------------------------------------------------------------------


class Claim(CommandModel):
    """Exclusive motion control of the device for ``client`` during ``ttl_s`` seconds; others'
    motion commands get ``claimed`` until ``release``, the TTL lapses, or the client's
    liveliness token ``<prefix>/clients/<client>`` disappears. Reads and e-stops are never
    refused. Claiming again (same client) renews the TTL."""

    op: Literal["claim"]
    client: ClientId
    ttl_s: Annotated[float, Field(gt=0, le=MAX_CLAIM_S)] = 60.0


class Release(CommandModel):
    """Give a claim back (only its holder may)."""

    op: Literal["release"]
    client: ClientId


class EndFollow(CommandModel):
    """End the device's follow stream now, rather than by letting it go stale: answered
    ``{"ok": true, "ended": true}`` at once (also when no stream was running), then the
    stream ends with a ``stream_stopped`` event (reason ``ended by <client>``, or ``ended``)
    and what a stale stream gets (a ZLAC706 in velocity mode 0 rpm), with no ``stream_stale``
    event. A device claimed by another client refuses it (``claimed``); an e-stopped one does
    not, since ending a stream moves nothing. A follow put after the ``stream_stopped``
    event starts a new stream. ``seq``, the client's count of what it sent this device's
    stream (targets and ends alike), orders the end against the targets: one of the client's
    targets with a lower ``seq`` was sent before the end and is dropped whenever it arrives
    (so is one with the end's own ``seq``: numbered alike, it cannot be ordered), one with a
    higher ``seq`` starts a new stream at once (without ``seq`` on both, a target within
    ``END_FENCE_S`` of the end is taken as sent before it)."""

    op: Literal["end_follow"]
    seq: FollowSeq | None = None


class ResetEstop(CommandModel):
    """Out of the gateway's e-stop: the device goes back to the power state it had before the
    stop and holds still. Enabled before, it is enabled again with its target where it is (a
    position device) or at 0 rpm (a speed device); off before, it stays off. Nothing moves
    until a new command. Answered with its state (at once when it was not e-stopped); a
    device claimed by another client refuses it (``claimed``). ``<prefix>/<gw>/estop/reset``
    (a put) resets every device of the gateway."""

    op: Literal["reset_estop"]


#: The ops every device's ``cmd`` key takes besides its kind's own.
GatewayCommand = Annotated[Claim | Release | EndFollow | ResetEstop, Field(discriminator="op")]


#: A value in SI: finite, and within ``MAX_SI`` (past it is a typo, never a joint's).
SiValue = Annotated[float, Field(ge=-MAX_SI, le=MAX_SI)]


class JointCommand(CommandModel):
    """Move a position joint to ``position``, or turn a velocity joint at ``velocity``, in SI
    (``docs/joints.md``): refused ``out_of_range`` beyond the joint's limits."""

    op: Literal["joint"]
    position: SiValue | None = None
    velocity: SiValue | None = None

    @model_validator(mode="after")
    def _one_value(self) -> JointCommand:
        if (self.position is None) == (self.velocity is None):
            raise ValueError("a joint command gives a position or a velocity, one of them")
        return self


class JointFollow(FollowModel):
    """A follow target in SI: ``joint`` (a position joint's position) or ``joint_velocity``
    (a velocity joint's velocity). Held within the joint's limits, never refused for them."""

    joint: SiValue | None = None
    joint_velocity: SiValue | None = None

    @model_validator(mode="before")
    @classmethod
    def _one_unit(cls, data: Any) -> Any:
        """A target in the device's own units beside one in SI is told as such, not as an
        extra field (``position: Extra inputs are not permitted``)."""
        if isinstance(data, dict) and (own := sorted(k for k in data if k in _device_units())):
            raise ValueError(
                f"a follow target in joint units takes joint or joint_velocity, not "
                f"{', '.join(map(str, own))} beside it (one in the device's own units gives "
                "those alone)"
            )
        return data

    @model_validator(mode="after")
    def _one_value(self) -> JointFollow:
        if (self.joint is None) == (self.joint_velocity is None):
            raise ValueError("a joint follow target gives joint or joint_velocity, one of them")
        return self


@functools.cache
def _device_units() -> frozenset[str]:
    """The keys of every family's own follow target (``position``, ``rpm`` …), those of every
    follow payload (client, seq) aside."""
    fields = {name for f in FAMILIES.values() for name in f.schema.FollowTarget.model_fields}
    return frozenset(fields - set(FollowModel.model_fields))


class BusGroupTarget(BaseModel):
    """One device of a bus ``group_move``: its name, target position, and (DS servos) the move
    time in ms. The position's range is the device kind's, checked by its driver."""

    model_config = CommandModel.model_config

    device: Name
    position: int
    time_ms: Annotated[int, Field(ge=0, le=65535)] | None = None


class BusGroupMove(CommandModel):
    """Start several devices of one bus together: one SYNC WRITE on a DS bus, one 0xF2 frame
    on an LA bus."""

    op: Literal["group_move"]
    targets: Annotated[list[BusGroupTarget], Field(min_length=1, max_length=64)]


class BusScan(CommandModel):
    """Which ids answer on the bus, and as what (for commissioning); all of the protocol's
    ids when ``ids`` is left out."""

    op: Literal["scan"]
    ids: (
        Annotated[
            list[Annotated[int, Field(ge=0, le=255)]], Field(min_length=1, max_length=MAX_SCAN_IDS)
        ]
        | None
    ) = None

    @model_validator(mode="after")
    def _distinct_ids(self) -> BusScan:
        if self.ids is not None:
            require_distinct(self.ids, "scan ids")
        return self


#: What ``<prefix>/<gw>/bus/<bus>/cmd`` takes.
BusCommand = Annotated[BusGroupMove | BusScan, Field(discriminator="op")]
BUS_COMMAND_ADAPTER: TypeAdapter[BusCommand] = TypeAdapter(BusCommand)


# --- telemetry (<prefix>/<gw>/dev/<device>/state) and follow targets (…/follow) -----------------

#: Each kind's telemetry model and follow payload, from its schema module.
TELEMETRY_MODELS: dict[str, type[TelemetryEnvelope]] = {
    kind: family.schema.TELEMETRY_MODEL for kind, family in FAMILIES.items()
}
#: Each kind's own follow target; every follow key also takes a joint's (``JointFollow``).
FOLLOW_MODELS: dict[str, type[CommandModel]] = {
    kind: family.schema.FollowTarget for kind, family in FAMILIES.items()
}
#: Any device's state, told apart by ``kind``.
Telemetry: TypeAlias = Annotated[  # type: ignore[valid-type]
    Union[tuple(TELEMETRY_MODELS.values())],  # noqa: UP007
    Field(discriminator="kind"),
]
TELEMETRY_ADAPTER: TypeAdapter[Any] = TypeAdapter(Telemetry)


# --- replies: every cmd queryable -----------------------------------------------------------------


#: The longest message of an error reply: room to spare for the gateway's, which
#: ``replies.error_reply`` cuts to it (naming every problem of a 59 KB command made one of
#: 263 KB, of a trajectory megabytes), and never a peer's megabytes.
MAX_MESSAGE = 4096


class ErrorDetail(Published):
    code: ErrorCode = Field(description="Stable, machine-readable reason.")
    message: str = Field(
        max_length=MAX_MESSAGE, description="Human-readable text; may change between versions."
    )


class ErrorReply(Published):
    """A refused or failed command."""

    ok: Literal[False]
    error: ErrorDetail


class OkReply(OpenPublished):
    """A command that was carried out; what else it carries depends on the op."""

    ok: Literal[True]


class StateReply(OkReply):
    """A device command's answer: the device's state after it, and for reads the raw bytes
    (``data``, hex) and the registers they hold in their units (``values``)."""

    state: Telemetry
    data: str | None = Field(default=None, description="Bytes read, as hex.")
    values: dict[str, Any] | None = Field(default=None, description="Registers read, by name.")


class ClaimReply(OkReply):
    claimed_by: ClientId
    expires_in_s: float


class ReleaseReply(OkReply):
    released: Literal[True]


class EndFollowReply(OkReply):
    ended: Literal[True]


class ScanFound(Published):
    id: int | None = Field(description="The id that answered.")
    protocol: ProtocolName
    reply: str = Field(description="The frame type it answered with.")


class ScanReply(OkReply):
    found: list[ScanFound]


#: Any reply of a device or bus ``cmd`` queryable.
Reply = StateReply | ClaimReply | ReleaseReply | EndFollowReply | ScanReply | ErrorReply
REPLY_ADAPTER: TypeAdapter[Reply] = TypeAdapter(Reply)


# --- info: <prefix>/<gw>/info ---------------------------------------------------------------------


class JointInfo(ReadByKey):
    """A device's joint: its name, type, unit, calibration (``si = offset + scale × raw``)
    and limits, in SI (``null``: none)."""

    model_config = FINITE

    name: Name
    type: JointType
    unit: Unit = Field(description='"m", "rad", or "raw" for a device without a joint table.')
    scale: float = Field(description="SI per raw unit.")
    offset: float = Field(description="SI value at raw 0.")
    min: float
    max: float
    max_velocity: float | None = Field(description="Unit per second.")
    max_acceleration: float | None = Field(description="Unit per second².")
    max_effort: float | None = Field(description="In effort_unit.")
    effort_unit: Unit | None = Field(description="The unit of the joint's effort.")
    raw_per_turn: float | None = Field(description="Raw position units in one turn.")
    configured: bool = Field(description="A joint table configured it (else raw units).")


class DeviceInfo(ReadByKey):
    name: Name
    kind: DeviceKind
    id: int
    joint: JointInfo | None = Field(
        default=None, description="The device as a joint; absent from gateways before joints."
    )
    state: Telemetry | None = Field(description="The last state published; null before the first.")

    @model_validator(mode="after")
    def _its_own_state(self) -> DeviceInfo:
        """A state naming another device or kind than its entry is no gateway's (a device's
        state key takes none either: ``client.messages.published_naming``)."""
        state = self.state
        if state is not None and (state.device, state.kind) != (self.name, self.kind):
            raise ValueError(f"the state of {self.name} ({self.kind}) names {state.device}")
        return self


class BusInfo(ReadByKey):
    name: Name
    protocol: ProtocolName
    devices: list[DeviceInfo]


#: The longest version an ``info`` reply carries: a release's (``0.1.0``) or a build's
#: (``0.1.1.dev12+g3f4a5b6.d20260315``) with room to spare, never a peer's megabytes.
MAX_VERSION = 128


class InfoReply(ReadByKey):
    """The gateway, its version, its buses and each bus's devices."""

    ok: Literal[True]
    gateway: Name
    version: str = Field(max_length=MAX_VERSION)
    buses: list[BusInfo]


# --- every joint: <prefix>/<gw>/joints -----------------------------------------------------------


class JointReading(ReadByKey):
    """One joint in the joints message: its values in SI and how fresh they are."""

    model_config = FINITE

    name: Name
    device: Name
    type: JointType
    unit: Unit
    position: float | None
    velocity: float | None
    effort: float | None
    ts: float | None = Field(
        description="When the values were read (as the device's state's ts); null: never."
    )
    stale: bool = Field(description="The values are older than a few poll periods.")


class JointsMessage(ReadByKey):
    """Every joint of a gateway in one message, published when any joint was read again,
    at most at its fastest poll rate."""

    model_config = FINITE

    gateway: Name
    ts: float = Field(description="When it was published, Unix seconds.")
    joints: list[JointReading]


# --- bus statistics: <prefix>/<gw>/bus/<bus>/stats ------------------------------------------------


class BusStatistics(Published):
    """``busgate.gateway.bus.stats.BusStats`` with ``ts`` and ``bus``, once a second. Counters
    are totals since the bus started; times are seconds."""

    model_config = FINITE

    ts: float = Field(description="Wall-clock time of the snapshot, Unix seconds.")
    bus: Name
    up: bool = Field(
        description="The port or interface is the gateway's: false while it is lost and "
        "being opened again."
    )
    frames_out: int
    frames_in: int
    bytes_out: int
    bytes_in: int
    timeouts: int = Field(description="Requests whose reply did not come in time.")
    retries: int = Field(description="Idempotent requests sent again after a timeout.")
    checksum_errors: int
    discarded_bytes: int = Field(description="Received bytes that were not part of a frame.")
    late_replies: int = Field(description="Replies that came after their deadline.")
    early_replies: int = Field(
        description="Replies read before their request could have left "
        "the wire at the bus's rate: a wrong baud rate, or an emulator "
        "without wire timing."
    )
    reconnects: int
    skipped_polls: int = Field(description="Polls left out to keep follow ticks on time.")
    busy_commands: int = Field(description="Commands refused with ``busy`` (queue full).")
    smallest_gap_s: float | None = Field(description="Shortest idle line seen between frames.")
    follow_error_p50_s: float | None = Field(description="Follow interval − period, median.")
    follow_error_p99_s: float | None = Field(description="Follow interval − period, p99.")
    follow_error_min_s: float | None = Field(description="Follow interval − period, least.")
    follow_intervals: int = Field(description="Follow intervals measured.")
    utilisation: Annotated[float, Field(ge=0, le=1)] = Field(description="Busy share of time.")
    uptime_s: float


# --- everything a device's cmd key takes ----------------------------------------------------------


def _device_commands(kind_module: Any) -> TypeAdapter[Any]:
    """The kind's own commands and the gateway-level ones, told apart by ``op``."""
    (union, *_) = get_args(kind_module.Command)
    members = (*get_args(union), Claim, Release, EndFollow, ResetEstop, JointCommand)
    return TypeAdapter(Annotated[Union[members], Field(discriminator="op")])  # type: ignore[arg-type]  # noqa: UP007


#: What ``<prefix>/<gw>/dev/<device>/cmd`` takes, per device kind.
DEVICE_COMMAND_ADAPTERS: dict[str, TypeAdapter[Any]] = {
    kind: _device_commands(family.schema) for kind, family in FAMILIES.items()
}
