"""JSON commands for Inspire LA linear actuators, one model per ``op``.

Ranges come from the codec's control table and constants (``busgate.codecs.inspire_la``);
the read and write rules are the codec's own ``check_span`` / ``check_write``, run as
validators, so a command the schema accepts is one the codec can encode.

Temperatures are degrees Celsius in JSON (0.1 °C steps) and tenths on the wire. The limit
and the rewarm temperature bound each other (limit ≥ rewarm + 5 °C); one command carries only
one of them, so each is checked here against the table's absolute bounds only, and the
cross check (``codec.check_temperature_limits``) is left to the driver or gateway that knows
the device's other, current value.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, Field, TypeAdapter, model_validator
from pydantic.fields import FieldInfo

from busgate.codecs import inspire_la as codec
from busgate.schemas.base import CommandModel, FollowModel, HexData, require_distinct
from busgate.schemas.joints import JointDeclaration
from busgate.schemas.telemetry import TelemetryEnvelope, fault_literal


def _register_range(name: str) -> FieldInfo:
    """``Field`` bounds of a register with a range in the manual."""
    register = codec.REGISTERS[name]
    return Field(ge=register.minimum, le=register.maximum)


def _temperature_range(name: str) -> FieldInfo:
    """``Field`` bounds in °C of a register stored in tenths of a degree."""
    register = codec.REGISTERS[name]
    tenths = codec.TENTHS_PER_DEGREE
    low, high = register.limits
    return Field(ge=low / tenths, le=high / tenths)


def _in_tenths(temp_c: float) -> float:
    codec.temperature_raw(temp_c)  # refuses steps finer than 0.1 °C
    return temp_c


Position = Annotated[int, _register_range("target_position")]
DeviceId = Annotated[int, Field(ge=codec.MIN_ID, le=codec.MAX_ID)]
Index = Annotated[int, Field(ge=0, le=codec.TABLE_SIZE - 1)]


class Move(CommandModel):
    """Go to ``position`` (0–2000) on a planned path; ``reply`` asks for the status frame."""

    op: Literal["move"]
    position: Position
    reply: bool = True


class Follow(CommandModel):
    """Follow-mode target: send one every 10–50 ms, at a fixed period."""

    op: Literal["follow"]
    position: Position
    reply: bool = True


class Enable(CommandModel):
    """Switch the power stage on (needed after ``estop``)."""

    op: Literal["enable"]


class Estop(CommandModel):
    """Switch the power stage off; the actuator moves again only after ``enable``."""

    op: Literal["estop"]


class Pause(CommandModel):
    """Switch the power stage off; the next target moves it again."""

    op: Literal["pause"]


class Save(CommandModel):
    """Copy the control table from RAM to flash (id, baud rate and limits survive power-off)."""

    op: Literal["save"]


class Status(CommandModel):
    """Ask for the status frame: target, position, temperature, current, force, faults."""

    op: Literal["status"]


class ClearFault(CommandModel):
    """Clear a latched over-current, stall or motor fault (over-temperature clears itself)."""

    op: Literal["clear_fault"]


class Read(CommandModel):
    """Read ``length`` bytes of the control table from ``index``."""

    op: Literal["read"]
    index: Index
    length: Annotated[int, Field(ge=1, le=codec.MAX_DATA)]

    @model_validator(mode="after")
    def _inside_table(self) -> Read:
        codec.check_span(self.index, self.length)
        return self


class Write(CommandModel):
    """Write raw little-endian bytes from ``index``; reserved and read-only bytes are refused,
    and a register written whole must get a value in its range."""

    op: Literal["write"]
    index: Index
    data: HexData

    @model_validator(mode="after")
    def _writable(self) -> Write:
        codec.check_write(self.index, bytes.fromhex(self.data))
        return self


class SetId(CommandModel):
    """Give the actuator a new id: in use at once, kept over power-off only after ``save``;
    an id another device of the bus has is refused (``out_of_range``)."""

    op: Literal["set_id"]
    new_id: Annotated[int, _register_range(codec.ID)]


class SetOvercurrent(CommandModel):
    """Set the over-current protection threshold in mA."""

    op: Literal["set_overcurrent"]
    current_ma: Annotated[int, _register_range(codec.OVERCURRENT_LIMIT)]


class SetOvertemp(CommandModel):
    """Set the over-temperature limit in °C (at least the rewarm temperature + 5 °C)."""

    op: Literal["set_overtemp"]
    temp_c: Annotated[float, _temperature_range(codec.OVERTEMP_LIMIT), AfterValidator(_in_tenths)]


class SetRewarm(CommandModel):
    """Set the temperature in °C below which an over-heated actuator works again."""

    op: Literal["set_rewarm"]
    temp_c: Annotated[
        float, _temperature_range(codec.REWARM_TEMPERATURE), AfterValidator(_in_tenths)
    ]


class SetBaudrate(CommandModel):
    """Set the UART baud rate; it takes effect after ``save`` and a power cycle."""

    op: Literal["set_baudrate"]
    baudrate: Literal[codec.BAUD_RATES]  # type: ignore[valid-type]


class ZeroForce(CommandModel):
    """Take the present force-sensor reading as zero (LAF / LASF)."""

    op: Literal["zero_force"]


class GroupTarget(BaseModel):
    """One actuator of a ``group_move`` or ``group_follow``."""

    model_config = CommandModel.model_config

    id: DeviceId
    position: Position


class _Group(CommandModel):
    targets: Annotated[list[GroupTarget], Field(min_length=1, max_length=codec.MAX_GROUP_TARGETS)]

    @model_validator(mode="after")
    def _distinct_ids(self) -> _Group:
        require_distinct([target.id for target in self.targets], "target ids")
        return self


class GroupMove(_Group):
    """Positioning targets for up to 15 actuators in one broadcast frame (no reply)."""

    op: Literal["group_move"]


class GroupFollow(_Group):
    """Follow-mode targets for up to 15 actuators in one broadcast frame (no reply)."""

    op: Literal["group_follow"]


Command = Annotated[
    Move | Follow | Enable | Estop | Pause | Save | Status | ClearFault | Read | Write | SetId
    | SetOvercurrent | SetOvertemp | SetRewarm | SetBaudrate | ZeroForce | GroupMove
    | GroupFollow,
    Field(discriminator="op"),
]  # fmt: skip
COMMAND_ADAPTER: TypeAdapter[Command] = TypeAdapter(Command)

#: The command that lets the device move again after a gateway e-stop (its driver's
#: ``reenable_op``; the SDK's ``Device.enable``).
REENABLE_COMMAND: dict[str, object] = {"op": "enable"}
#: Ops other families have, and what does their deed here (an unknown op's refusal says it).
OPS_ELSEWHERE: dict[str, str] = {
    "disable": "`pause` switches its power stage off (the next target moves it again); "
    "`estop` too, until an `enable`",
}


# --- the follow key and telemetry ---------------------------------------------------------------


class FollowTarget(FollowModel):
    """What ``<prefix>/<gw>/dev/<device>/follow`` takes: the target position, and the sending
    client and its ``seq`` (the latest target is sent at the device's follow period)."""

    position: Position


FaultName = fault_literal(codec.Fault)


class InspireLaTelemetry(TelemetryEnvelope):
    """An Inspire LA actuator: its last status frame, the commanded power stage, and the
    protection limits as last read or confirmed (at first the manual's defaults)."""

    kind: Literal["inspire_la"]
    position: int | None = Field(description="Present position, raw stroke units 0–2000.")
    target: int | None = Field(description="Target position the actuator reports, 0–2000.")
    temperature_c: int | None = Field(description="Actuator temperature, °C.")
    current_ma: int | None = Field(description="Motor current, mA.")
    force_g: int | None = Field(description="Force sensor reading, g (LAF/LASF models only).")
    faults: list[FaultName] = Field(description="Latched faults by name; empty when healthy.")  # type: ignore[valid-type]
    power: Literal["on", "paused", "estopped"] = Field(
        description="Power stage as commanded: paused until the next target, estopped until enable."
    )
    overcurrent_limit_ma: int = Field(description="Over-current protection threshold, mA.")
    overtemp_limit_c: float = Field(description="Over-temperature limit, °C (0.1 °C steps).")
    rewarm_temperature_c: float = Field(
        description="Temperature below which an over-heated actuator works again, °C."
    )


TELEMETRY_MODEL = InspireLaTelemetry

_TARGET = codec.REGISTERS["target_position"]
#: The actuator as a joint (``busgate.schemas.joints``): a stroke position, no measured speed,
#: the force sensor's reading as its effort (g of force to newtons).
JOINT = JointDeclaration(
    raw_range=_TARGET.limits,
    position="position",
    target="target",
    move=("move", "position"),
    follow_position="position",
    effort="force_g",
    effort_unit="N",
    effort_per_raw=9.80665e-3,
)
