"""JSON commands for the ZLAC706 hub-motor servo driver, one model per ``op``.

The same commands drive both wire protocols (CAN and RS232); the drivers
``busgate.gateway.drivers.zlac706_can`` / ``zlac706_rs232`` map them to frames. Ranges are the
ones both protocols share (``busgate.codecs.zlac706_common``) or the widest wire's (CAN's i32
position); a value that only CAN can carry (a position or gain beyond 16 bits, on RS232)
is refused by the RS232 codec with ``EncodeError``, as are the ops one protocol lacks
(``monitor`` on CAN, current-loop gains on RS232) by its driver.

Units: speeds in rpm (float; truncated toward zero on the wire, the RS232 speed limit
rounded), torque as current in A (float, 3.2 mA steps), ramps in ms. Ramps must be whole
multiples of 100 ms, the wire's unit: a command is refused rather than silently changed.
"""

from __future__ import annotations

import warnings
from typing import Annotated, Literal

from pydantic import Field, Strict, TypeAdapter, model_validator

from busgate.codecs import zlac706_can as can
from busgate.codecs import zlac706_common as common
from busgate.schemas.base import CommandModel, FollowModel, Published
from busgate.schemas.joints import JointDeclaration
from busgate.schemas.telemetry import TelemetryEnvelope, fault_literal

_POSITION = can.REGISTERS["target_position"]

Rpm = Annotated[float, Field(ge=-common.MAX_SPEED_RPM, le=common.MAX_SPEED_RPM)]
#: A position target in encoder pulses (CAN's i32).
Position = Annotated[int, Field(ge=_POSITION.minimum, le=_POSITION.maximum)]
RampMs = Annotated[int, Field(ge=0, le=common.RAMP_MAX_MS, multiple_of=common.RAMP_STEP_MS)]


#: An enum named by its value, as JSON names it: the API validates the object it parsed from
#: the payload, where strict mode would take only the enum member itself.
ByValue = Strict(False)


class SetMode(CommandModel):
    """Choose the work mode; on both protocols the first step of any sequence."""

    op: Literal["set_mode"]
    mode: Annotated[common.Mode, ByValue]


class Enable(CommandModel):
    """Enable the motor (the shaft locks; in speed mode a preset speed starts at once)."""

    op: Literal["enable"]


class Disable(CommandModel):
    """Release the motor (stop; the shaft turns freely)."""

    op: Literal["disable"]


class SetPositionMode(CommandModel):
    """Targets of ``move`` are relative to the present position, or absolute."""

    op: Literal["set_position_mode"]
    relative: bool


class Move(CommandModel):
    """Position-mode target in pulses (i32); the motor must be enabled first."""

    op: Literal["move"]
    position: Position


class Velocity(CommandModel):
    """Speed-mode target; with feed-forward gain 1 it must be refreshed (CAN 500 ms)."""

    op: Literal["velocity"]
    rpm: Rpm


class Torque(CommandModel):
    """Torque-mode target as output current, ±24 A."""

    op: Literal["torque"]
    current_a: Annotated[float, Field(ge=-common.MAX_CURRENT_A, le=common.MAX_CURRENT_A)]


class SetPositionRamp(CommandModel):
    """Position-mode acceleration and deceleration times (0 to top speed)."""

    op: Literal["set_position_ramp"]
    accel_ms: RampMs
    decel_ms: RampMs


class SetVelocityRamp(CommandModel):
    """Speed-mode acceleration and deceleration times (0 to top speed)."""

    op: Literal["set_velocity_ramp"]
    accel_ms: RampMs
    decel_ms: RampMs


class SetMaxSpeed(CommandModel):
    """Position mode's top (cruise) speed."""

    op: Literal["set_max_speed"]
    rpm: Annotated[float, Field(ge=0, le=common.MAX_SPEED_RPM)]


class ClearAlarm(CommandModel):
    """Reset the drive's alarm: only with its run signal (the enable) known to be off, so
    disable first; an alarm reset with the run signal on starts the drive again suddenly, the
    manual warns."""

    op: Literal["clear_alarm"]


class Home(CommandModel):
    """Search the encoder's Z signal (hub motors have none: nothing happens)."""

    op: Literal["home"]


class SetRatedCurrent(CommandModel):
    op: Literal["set_rated_current"]
    current_ma: Annotated[int, Field(ge=0, le=common.RATED_CURRENT_MAX_MA)]


class SetGain(CommandModel):
    op: Literal["set_gain"]
    gain: Annotated[common.Gain, ByValue]
    value: Annotated[int, Field(ge=common.GAIN_MIN, le=common.GAIN_MAX)]


# The API names the field ``register``, which shadows ``BaseModel.register`` (ABCMeta's
# virtual-subclass hook, never called on a command); pydantic warns at class creation only.
# Without the explicit ``Field(...)`` pydantic takes that inherited method for the field's
# default, and a write without a register would be accepted.
with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message='Field name "register"', category=UserWarning)

    class Write(CommandModel):
        """Raw register write; the register must be in the protocol's table (driver checks)."""

        op: Literal["write"]
        register: Annotated[int, Field(ge=0, le=0xFF)] = Field(...)
        value: Annotated[int, Field(ge=can.I32_MIN, le=can.I32_MAX)]


class Monitor(CommandModel):
    """RS232 only: ask for status, bus voltage, current, speed and positions."""

    op: Literal["monitor"]


Command = Annotated[
    SetMode
    | Enable
    | Disable
    | SetPositionMode
    | Move
    | Velocity
    | Torque
    | SetPositionRamp
    | SetVelocityRamp
    | SetMaxSpeed
    | ClearAlarm
    | Home
    | SetRatedCurrent
    | SetGain
    | Write
    | Monitor,
    Field(discriminator="op"),
]
COMMAND_ADAPTER: TypeAdapter[Command] = TypeAdapter(Command)

#: The command that lets the device move again after a gateway e-stop (its driver's
#: ``reenable_op``; the SDK's ``Device.enable``).
REENABLE_COMMAND: dict[str, object] = {"op": "enable"}
#: Ops other families have, and what does their deed here (an unknown op's refusal says it).
OPS_ELSEWHERE: dict[str, str] = {
    "pause": "`disable` releases the motor (the shaft turns freely)",
    "estop": "`disable` releases the motor; the gateway's e-stop key stops every device",
}


# --- the follow key and telemetry ---------------------------------------------------------------


class FollowTarget(FollowModel):
    """What ``<prefix>/<gw>/dev/<device>/follow`` takes: a speed in velocity mode, or a
    position target in absolute position mode (CAN: one frame a target), and the sending
    client and its ``seq`` (the latest target is sent at the device's follow period)."""

    rpm: Rpm | None = None
    position: Position | None = None

    @model_validator(mode="after")
    def _one_target(self) -> FollowTarget:
        if (self.rpm is None) == (self.position is None):
            raise ValueError("a ZLAC706 follow target gives rpm or position, one of them")
        return self


#: The alarm bits that are faults (``AlarmFlags.faults`` leaves out running and external control).
FaultName = fault_literal(f for f in common.AlarmFlags if f.faults)


class Ramp(Published):
    """Acceleration and deceleration times from 0 to top speed, in ms (100 ms steps)."""

    accel_ms: Annotated[int, Field(ge=0)]
    decel_ms: Annotated[int, Field(ge=0)]


class Zlac706Telemetry(TelemetryEnvelope):
    """A ZLAC706 hub-motor driver: the settings it acknowledged and, from heartbeats (CAN) or
    the monitor reply (RS232), what it measured."""

    kind: Literal["zlac706"]
    mode: common.Mode | None = Field(description="Work mode as acknowledged.")
    position_mode: Literal["relative", "absolute"] | None = Field(
        description="How position targets are taken."
    )
    target: int | None = Field(description="Position target, encoder pulses.")
    target_speed_rpm: float | None = Field(description="Speed target, rpm.")
    target_current_a: float | None = Field(description="Torque-mode current target, A.")
    position_ramp: Ramp | None = Field(description="Position-mode ramps.")
    velocity_ramp: Ramp | None = Field(description="Velocity-mode ramps.")
    max_speed_rpm: float | None = Field(description="Position mode's top speed, rpm.")
    measured: bool = Field(
        description="Measured values have arrived (false on CAN until the first heartbeat)."
    )
    position: int | None = Field(description="Feedback position, encoder pulses.")
    current_ma: int | None = Field(description="Output current, mA.")
    speed_rpm: float | None = Field(description="Measured speed, rpm.")
    voltage_v: int | None = Field(
        default=None, description="DC bus voltage, V (±2 V; RS232 only: absent on CAN)."
    )
    faults: list[FaultName] = Field(description="Alarm bits by name; empty when healthy.")  # type: ignore[valid-type]


TELEMETRY_MODEL = Zlac706Telemetry

#: The hub motor as a joint (``busgate.schemas.joints``): a wheel commanded by speed (velocity
#: mode; ``type = "position"`` for position mode; its follow stream carries what its mode
#: takes, positions in absolute position mode), its position counted in encoder pulses
#: (10000 a turn by the manual's note 6: ``raw_per_turn`` in the table when yours differs),
#: speeds in rpm (exact in rad/s), its output current as its effort, bounded in torque mode.
JOINT = JointDeclaration(
    raw_range=_POSITION.limits,
    position="position",
    target="target",
    move=("move", "position"),
    types=("velocity", "position"),
    speed_rpm="speed_rpm",
    target_speed_rpm="target_speed_rpm",
    turn=("velocity", "rpm"),
    follow_position="position",
    follow_velocity="rpm",
    raw_per_turn=common.PULSES_PER_TURN,
    effort="current_ma",
    effort_unit="A",
    effort_per_raw=1e-3,
    effort_limited=True,
    top_speed=common.MAX_SPEED_RPM,
)
