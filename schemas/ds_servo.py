"""JSON commands for DS serial-bus servos, one model per ``op``.

Ranges come from the codec's control table and constants (``busgate.codecs.ds_servo``);
the read and write address rules are the codec's own ``check_read`` / ``check_write``, run
as validators, so a command the schema accepts is one the codec can encode.

Ops beyond the manual's instruction list: ``store_preset {n}`` (the manual's "set preset n":
writing the preset address alone stores the present position). No ``estop``: the manual
names address 0x30 "lock flag (e-stop)" but documents none of its values, and an e-stop that
writes a guessed value may not stop anything; ``torque {on: false}`` is the documented way to
release a servo, and ``write`` reaches 0x30 for firmware whose values are known.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field, TypeAdapter, model_validator
from pydantic.fields import FieldInfo

from busgate.codecs import ds_servo as codec
from busgate.schemas.base import CommandModel, FollowModel, HexData, require_distinct
from busgate.schemas.joints import JointDeclaration
from busgate.schemas.telemetry import TelemetryEnvelope, fault_literal


def _register_range(name: str) -> FieldInfo:
    """``Field`` bounds of an unsigned register: the manual's range, else its type's."""
    register = codec.REGISTERS[name]
    low = 0 if register.minimum is None else register.minimum
    high = (1 << 8 * register.size) - 1 if register.maximum is None else register.maximum
    return Field(ge=low, le=high)


Position = Annotated[int, _register_range("target_position")]
#: Move time in ms; 0 (the register's default) moves at the fastest speed.
TimeMs = Annotated[int, _register_range("move_time")]
ServoId = Annotated[int, Field(ge=codec.MIN_ID, le=codec.MAX_ID)]
PresetNumber = Annotated[int, Field(ge=1, le=len(codec.PRESET_ADDRESSES))]
DEFAULT_TIME_MS: int = codec.REGISTERS.default("move_time")


class Ping(CommandModel):
    """Ask the servo for its status flags."""

    op: Literal["ping"]


class Read(CommandModel):
    """Read ``length`` bytes of the control table from ``address``."""

    op: Literal["read"]
    address: Annotated[int, Field(ge=0, le=codec.TABLE_END - 1)]
    length: Annotated[int, Field(ge=1, le=codec.TABLE_END)]

    @model_validator(mode="after")
    def _inside_table(self) -> Read:
        codec.check_read(self.address, self.length)
        return self


class Write(CommandModel):
    """Write raw big-endian bytes to whole, writable registers starting at ``address``."""

    op: Literal["write"]
    address: Annotated[int, Field(ge=0, le=codec.TABLE_END - 1)]
    data: HexData

    @model_validator(mode="after")
    def _writable(self) -> Write:
        codec.check_write(self.address, bytes.fromhex(self.data))
        return self


class Move(CommandModel):
    """Move to ``position`` in ``time_ms``; ``deferred`` stores it until ``action``."""

    op: Literal["move"]
    position: Position
    time_ms: TimeMs = DEFAULT_TIME_MS
    deferred: bool = False


class Action(CommandModel):
    """Start every deferred move at once (broadcast)."""

    op: Literal["action"]


class GroupTarget(BaseModel):
    """One servo of a ``group_move``."""

    model_config = CommandModel.model_config

    id: ServoId
    position: Position
    time_ms: TimeMs = DEFAULT_TIME_MS


class GroupMove(CommandModel):
    """Move several servos with one broadcast SYNC WRITE frame."""

    op: Literal["group_move"]
    targets: Annotated[list[GroupTarget], Field(min_length=1, max_length=codec.MAX_SYNC_TARGETS)]

    @model_validator(mode="after")
    def _distinct_ids(self) -> GroupMove:
        require_distinct([target.id for target in self.targets], "target ids")
        return self


class Torque(CommandModel):
    """Switch the motor's torque on or off (off releases the shaft)."""

    op: Literal["torque"]
    on: bool


class SetId(CommandModel):
    """Give the servo a new id (takes effect at once, kept across power cycles); an id
    another device of the bus has is refused (``out_of_range``)."""

    op: Literal["set_id"]
    new_id: Annotated[int, _register_range("servo_id")]


class GotoPreset(CommandModel):
    """Move to stored preset position ``n``."""

    op: Literal["goto_preset"]
    n: PresetNumber


class StorePreset(CommandModel):
    """Store the present position as preset ``n``."""

    op: Literal["store_preset"]
    n: PresetNumber


class Reset(CommandModel):
    """Restore the factory settings, the id (1) and torque on included: refused
    (``out_of_range``) while another servo of the bus has id 1, and (``estopped``) while the
    gateway holds this one e-stopped."""

    op: Literal["reset"]


Command = Annotated[
    Ping
    | Read
    | Write
    | Move
    | Action
    | GroupMove
    | Torque
    | SetId
    | GotoPreset
    | StorePreset
    | Reset,
    Field(discriminator="op"),
]
COMMAND_ADAPTER: TypeAdapter[Command] = TypeAdapter(Command)

#: The command that lets the device move again after a gateway e-stop (its driver's
#: ``reenable_op``; the SDK's ``Device.enable``).
REENABLE_COMMAND: dict[str, object] = {"op": "torque", "on": True}
#: Ops other families have, and what does their deed here (an unknown op's refusal says it).
OPS_ELSEWHERE: dict[str, str] = {
    "enable": '`torque` with `"on": true` switches its torque on',
    "disable": '`torque` with `"on": false` switches its torque off (the shaft turns freely)',
}


# --- the follow key and telemetry ---------------------------------------------------------------


class FollowTarget(FollowModel):
    """What ``<prefix>/<gw>/dev/<device>/follow`` takes: one absolute position, and the sending
    client and its ``seq`` (the latest target is sent at the device's follow period)."""

    position: Position


FaultName = fault_literal(codec.ServoStatus)


class DsServoTelemetry(TelemetryEnvelope):
    """A DS serial servo: its last poll, what it confirmed, and its status-byte faults."""

    kind: Literal["ds_servo"]
    position: int | None = Field(description="Present position, raw 0–4095 (one turn).")
    speed_raw: int | None = Field(
        description="Speed register, raw: the manual does not document its unit."
    )
    current_ma: int | None = Field(description="Motor current, mA.")
    temperature_c: int | None = Field(description="Servo temperature, °C.")
    target: int | None = Field(description="Target position last confirmed or sent, 0–4095.")
    pending_target: int | None = Field(
        description="A deferred move's target waiting for ``action``, 0–4095."
    )
    torque_on: bool | None = Field(description="Torque enabled (false: the shaft is free).")
    faults: list[FaultName] = Field(description="Status-byte faults by name; empty when healthy.")  # type: ignore[valid-type]


TELEMETRY_MODEL = DsServoTelemetry

_TARGET = codec.REGISTERS["target_position"]
#: The servo as a joint (``busgate.schemas.joints``): one turn is 4096 counts; its speed
#: register's unit is undocumented, so its velocity is not known; its motor current is its
#: effort, in amperes.
JOINT = JointDeclaration(
    raw_range=_TARGET.limits,
    position="position",
    target="target",
    move=("move", "position"),
    follow_position="position",
    raw_per_turn=_TARGET.limits[1] + 1,
    effort="current_ma",
    effort_unit="A",
    effort_per_raw=1e-3,
)
