"""ZLAC706 RS232 driver: a ``busgate.schemas.zlac706`` command becomes the RS232 frames that do it.

The link is point to point, so ``device_id`` is ignored (the CLI refuses ``--id``). Every op
is one frame except ``move``: a 32-bit position goes as its high 16 bits (register 50), then
its low 16 bits (register 05), in that order (manual 8.2.1 note 4). Speeds truncate toward
zero like the manual's speed table; the position-mode speed limit rounds (note 8: 60 rpm →
0x00A4). RS232 has no current-loop gains: ``set_gain`` of ``current_kp``/``current_kd`` is
refused here. Values wider than 16 bits are refused by the codec's encoder.

``Zlac706Rs232Driver`` (below the table) is the gateway's driver; its state machine is shared
with CAN (``zlac706_state``). What is RS232's own:

1. ``poll`` is the monitor request (and ``init``'s first, nothing preset after it); its
   eight frames give the status word
   (alarms → faults; its running bit says whether the motor is enabled, so a device that
   rebooted or dropped out on a fault is known to be disabled), bus voltage, current, speed
   and the feedback position.
2. The keep-alive is the monitor, every 0.8 s (the manual: at least once a second).
3. An acknowledgement (``addr addr``) names the register only; the value the state takes is
   the one written.
4. A target's low half (register 05) is joined to the high half written before it; with no
   high half known (none written since the gateway started, or the drive rebooted) the target
   is not known either: ``None``, which a limited joint refuses.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from busgate.codecs import zlac706_common as common
from busgate.codecs import zlac706_rs232 as codec
from busgate.codecs.errors import CodecError
from busgate.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.zlac706 import Zlac706Driver
from busgate.gateway.drivers.zlac706_state import Role, RoleOf, reverse
from busgate.schemas import zlac706 as schema

Reg = codec.Rs232Register
Frame = codec.Write | codec.MonitorRequest

_CONTROL_MODES = {
    common.Mode.POSITION: codec.ControlMode.PC_POSITION,
    common.Mode.VELOCITY: codec.ControlMode.PC_SPEED,
    common.Mode.TORQUE: codec.ControlMode.PC_TORQUE,
}


def _one(make: Callable[[Any], Frame]) -> Callable[[Any], list[Frame]]:
    return lambda command: [make(command)]


def _fixed(register: Reg, value: int) -> Callable[[Any], list[Frame]]:
    return _one(lambda _command: codec.Write(register, value))


def _ramp(register: Reg) -> Callable[[Any], list[Frame]]:
    return _one(lambda c: codec.Write(register, common.ramp_word(c.accel_ms, c.decel_ms)))


def _move(command: schema.Move) -> list[Frame]:
    high, low = codec.split_position(command.position)
    return [codec.Write(Reg.POSITION_HIGH, high), codec.Write(Reg.POSITION_LOW, low)]


def _gain(command: schema.SetGain) -> list[Frame]:
    register = codec.GAIN_REGISTERS.get(command.gain)
    if register is None:
        raise CommandError(f"the RS232 protocol has no {command.gain.value} gain (CAN has)")
    return [codec.Write(register, command.value)]


def _raw_write(command: schema.Write) -> list[Frame]:
    if command.register not in codec.WRITABLE:
        raise CommandError(
            f"register {command.register:#04x} is not a writable ZLAC706 RS232 register"
        )
    return [codec.Write(command.register, command.value)]


_FRAMES_OF: dict[type, Callable[[Any], list[Frame]]] = {
    schema.SetMode: _one(lambda c: codec.Write(Reg.MODE, _CONTROL_MODES[c.mode])),
    schema.Enable: _fixed(Reg.ENABLE, codec.EnableCode.ENABLE),
    schema.Disable: _fixed(Reg.ENABLE, codec.EnableCode.DISABLE),
    schema.SetPositionMode: _one(
        lambda c: codec.Write(
            Reg.POSITION_MODE,
            codec.PositionMode.RELATIVE if c.relative else codec.PositionMode.ABSOLUTE,
        )
    ),
    schema.Move: _move,
    schema.Velocity: _one(lambda c: codec.Write(Reg.SPEED, common.speed_raw_truncated(c.rpm))),
    schema.Torque: _one(
        lambda c: codec.Write(Reg.TORQUE, common.torque_raw_from_amps(c.current_a))
    ),
    schema.SetPositionRamp: _ramp(Reg.POSITION_RAMP),
    schema.SetVelocityRamp: _ramp(Reg.SPEED_RAMP),
    schema.SetMaxSpeed: _one(
        lambda c: codec.Write(Reg.SPEED_LIMIT, common.speed_raw_rounded(c.rpm))
    ),
    schema.ClearAlarm: _fixed(Reg.CLEAR_FAULT, 0),
    schema.Home: _fixed(Reg.ORIGIN, 0),
    schema.SetRatedCurrent: _one(lambda c: codec.Write(Reg.RATED_CURRENT, c.current_ma)),
    schema.SetGain: _gain,
    schema.Write: _raw_write,
    schema.Monitor: _one(lambda _command: codec.MonitorRequest()),
}


def frames_for(command: Any, device_id: int) -> list[Frame]:
    """The frames, in order, that carry out ``command``; ``device_id`` is unused (point to point).

    >>> cmd = schema.COMMAND_ADAPTER.validate_json('{"op":"move","position":10000}')
    >>> [codec.encode(f).hex() for f in frames_for(cmd, 1)]
    ['50000050', '0527103c']
    """
    return _FRAMES_OF[type(command)](command)


# --- the driver ------------------------------------------------------------------------------

_MODE_OF = reverse(_CONTROL_MODES)  # external pulses (C0) maps to no mode: PC targets ignored

ROLES: dict[int, RoleOf] = {
    Reg.MODE: RoleOf(Role.MODE, lambda raw, _s: _MODE_OF.get(raw)),
    Reg.ENABLE: RoleOf(Role.ENABLE, lambda raw, _s: raw == codec.EnableCode.ENABLE),
    Reg.POSITION_MODE: RoleOf(
        Role.POSITION_MODE, lambda raw, _s: raw == codec.PositionMode.RELATIVE
    ),
    Reg.POSITION_HIGH: RoleOf(Role.POSITION_HIGH),
    # The low half completes the target: joined to the high half written before it (rule 4).
    Reg.POSITION_LOW: RoleOf(
        Role.POSITION,
        lambda raw, s: (
            None if s.position_high is None else codec.join_position(s.position_high, raw)
        ),
    ),
    Reg.SPEED: RoleOf(Role.SPEED),
    Reg.TORQUE: RoleOf(Role.TORQUE),
    Reg.POSITION_RAMP: RoleOf(Role.POSITION_RAMP),
    Reg.SPEED_RAMP: RoleOf(Role.SPEED_RAMP),
    Reg.SPEED_LIMIT: RoleOf(Role.MAX_SPEED),
    Reg.CLEAR_FAULT: RoleOf(Role.ALARM_RESET),
    Reg.ORIGIN: RoleOf(Role.ONE_SHOT),
}

_MONITOR = Request.of(codec, codec.MonitorRequest(), idempotent=True)


class Zlac706Rs232Driver(Zlac706Driver):
    """The ZLAC706 at the other end of an RS232 link."""

    protocol: ClassVar[str] = "zlac706_rs232"

    frames = staticmethod(frames_for)
    roles: ClassVar[dict[int, RoleOf]] = ROLES
    #: The manual asks for a monitor at least once a second in speed mode; 0.2 s of margin.
    keepalive_period_s: ClassVar[float] = 0.8
    streams_positions: ClassVar[bool] = False
    measured_names: ClassVar[tuple[str, ...]] = ("position", "current_ma", "speed_rpm", "voltage_v")

    def poll(self) -> list[Request]:
        return [_MONITOR]

    def init(self) -> list[Request]:
        """The monitor; then, unless a client enabled the motor since, nothing preset (0 rpm,
        0 A, as CAN's ``init``; harmless to a motor that is off or in another mode), so that
        no speed or torque preset before the gateway came starts the motor at the next enable
        (manual 8.1.2 (4))."""
        if self.machine.settings.enabled:
            return self.poll()
        return self.poll() + self.nothing_preset()

    @classmethod
    def probe(cls, device_id: int) -> Request:
        """The monitor request: it reads, and the one driver on the line answers."""
        return Request.of(codec, codec.MonitorRequest())  # a scan sends it once: not idempotent

    def keepalive_request(self) -> Request:
        return Request.of(codec, codec.MonitorRequest())  # a scan sends it once: not idempotent

    def refreshes_keepalive(self, request: Request) -> bool:
        return isinstance(request.frame, codec.MonitorRequest)

    def apply(self, request: Request, reply: tuple[object, ...], now: float) -> dict[str, Any]:
        if isinstance(request.frame, codec.Write):
            self.acknowledged(request.frame)
            return {}
        try:
            monitor = codec.assemble_monitor(reply)
        except CodecError:
            return {}  # eight frames, but one of them twice: take none rather than guess
        self._take_monitor(monitor, now)
        return {}

    def _take_monitor(self, monitor: codec.MonitorReply, now: float) -> None:
        self.take_position(monitor.feedback_position_raw, now)
        self.measured.update(
            current_ma=round(monitor.current_a * 1000),
            speed_rpm=monitor.speed_rpm,
            voltage_v=monitor.voltage_v,
        )
        enabled = common.AlarmFlags.RUNNING in monitor.alarms
        self.machine.acknowledged({"enabled": enabled})  # the run signal is what was written
        self.take_alarms(monitor.alarms)
