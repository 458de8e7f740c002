"""ZLAC706 CAN driver: a ``busgate.schemas.zlac706`` command becomes the CAN frames that do it.

Every op is one register write to ``device_id`` (0 writes to every node with ``DA``). Unit
conversions are the shared ones (``busgate.codecs.zlac706_common``): speeds truncate toward
zero, as the manual's 1000 rpm → 0x0AAA does for the speed target and the trapezoid speed
alike. The order a mode needs (mode, ramps, enable, then target: a position target sent
before enable is ignored) and the speed keep-alive are the gateway's state machine, not this
stateless mapping. ``monitor`` exists on RS232 only: on CAN the driver's heartbeat reports
position, current and speed unasked.

``Zlac706CanDriver`` (below the table) is the gateway's driver; its state machine is shared
with RS232 (``zlac706_state``). What is CAN's own:

1. There is no read: ``poll`` is empty, measured values come only from heartbeats
   (``unsolicited``), and alarm reports replace the heartbeats while the device is in alarm.
2. Liveness: with heartbeats expected (``heartbeat_ms`` > 0) they alone bring the node online,
   and ``check_heartbeat(now)`` (called by the runner) marks it offline after 3 intervals
   without one; an acknowledged write alone then proves the node answers but not that it
   reports. A heartbeat, in turn, proves the node reports but not that it takes writes: it
   leaves the count of writes gone unanswered as it is, and a node that answered none of
   ``OFFLINE_AFTER`` writes in a row is offline until one is answered, heartbeats or not (a
   base's wheel that takes no speed stops its base). With none expected, the node is online
   while it acknowledges writes, and the telemetry says that measured values are
   unavailable (``"measured": false``).
3. A heartbeat is two frames, position and then current and speed, and the device's state is
   news once both have come (``unsolicited``): a look at the bus taken between them would
   otherwise publish one heartbeat's position with the one before's speed, and a state a
   fraction of a millisecond later with no move, which a client taking positions apart for
   a velocity reads as a stop. A half that comes again before its other (a frame lost, or a
   device that sends one) is news at once; an alarm report is news at once. A heartbeat's
   first frame begins a new reading (``begins_reading``): one look that takes two heartbeats
   publishes the first's state before the second's frames are taken in.
4. ``init`` re-writes the acknowledged work mode (harmless, and echoed ``FB``); while the
   power stage is not known, it releases the motor (control word ``0F``), whether the mode
   is known or not: a gateway that does not know what the motor is doing stops it rather
   than guesses (but not once a client enabled it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from busgate.codecs import zlac706_can as codec
from busgate.codecs import zlac706_common as common
from busgate.errors import CommandError, DeviceRefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import OFFLINE_AFTER
from busgate.gateway.drivers.zlac706 import Zlac706Driver
from busgate.gateway.drivers.zlac706_state import Role, RoleOf, reverse
from busgate.schemas import zlac706 as schema

Reg = codec.CanRegister

_WORK_MODES = {
    common.Mode.POSITION: codec.WorkMode.POSITION,
    common.Mode.VELOCITY: codec.WorkMode.SPEED,
    common.Mode.TORQUE: codec.WorkMode.TORQUE,
}


def _fixed(register: Reg, value: int) -> Callable[[Any, int], codec.Write]:
    return lambda _command, device_id: codec.Write(device_id, register, value)


def _ramp(register: Reg) -> Callable[[Any, int], codec.Write]:
    return lambda c, device_id: codec.Write(
        device_id, register, common.ramp_word(c.accel_ms, c.decel_ms)
    )


def _raw_write(command: schema.Write, device_id: int) -> codec.Write:
    if codec.REGISTERS.at(command.register) is None:
        raise CommandError(f"register {command.register:#04x} is not in the ZLAC706 CAN table")
    return codec.Write(device_id, command.register, command.value)


def _monitor(_command: schema.Monitor, _device_id: int) -> codec.Write:
    raise CommandError(
        "monitor is an RS232 request; on CAN the driver's heartbeat reports position, "
        "current and speed (enable it with the vendor tool)"
    )


_FRAME_FOR: dict[type, Callable[[Any, int], codec.Write]] = {
    schema.SetMode: lambda c, d: codec.Write(d, Reg.WORK_MODE, _WORK_MODES[c.mode]),
    schema.Enable: _fixed(Reg.CONTROL_WORD, codec.ControlWord.ENABLE),
    schema.Disable: _fixed(Reg.CONTROL_WORD, codec.ControlWord.RELEASE),
    schema.SetPositionMode: lambda c, d: codec.Write(
        d,
        Reg.POSITION_MODE,
        codec.PositionMode.RELATIVE if c.relative else codec.PositionMode.ABSOLUTE,
    ),
    schema.Move: lambda c, d: codec.Write(d, Reg.TARGET_POSITION, c.position),
    schema.Velocity: lambda c, d: codec.Write(
        d, Reg.TARGET_SPEED, common.speed_raw_truncated(c.rpm)
    ),
    schema.Torque: lambda c, d: codec.Write(
        d, Reg.TARGET_TORQUE, common.torque_raw_from_amps(c.current_a)
    ),
    schema.SetPositionRamp: _ramp(Reg.POSITION_RAMP),
    schema.SetVelocityRamp: _ramp(Reg.SPEED_RAMP),
    schema.SetMaxSpeed: lambda c, d: codec.Write(
        d, Reg.MAX_SPEED, common.speed_raw_truncated(c.rpm)
    ),
    schema.ClearAlarm: _fixed(Reg.ALARM_RESET, codec.AlarmReset.RESET),
    schema.Home: _fixed(Reg.ORIGIN, codec.Origin.SEARCH),
    schema.SetRatedCurrent: lambda c, d: codec.Write(d, Reg.RATED_CURRENT, c.current_ma),
    schema.SetGain: lambda c, d: codec.Write(d, codec.GAIN_REGISTERS[c.gain], c.value),
    schema.Write: _raw_write,
    schema.Monitor: _monitor,
}


def frames_for(command: Any, device_id: int) -> list[codec.Write]:
    """The frames, in order, that carry out ``command`` on node ``device_id`` (0: all nodes).

    >>> cmd = schema.COMMAND_ADAPTER.validate_json('{"op":"velocity","rpm":-1000}')
    >>> [str(codec.encode(f)) for f in frames_for(cmd, 1)]
    ['001#00fa0011fffff556']
    """
    return [_FRAME_FOR[type(command)](command, device_id)]


# --- the driver ------------------------------------------------------------------------------

_MODE_OF = reverse(_WORK_MODES)
#: Heartbeats missed in a row before the node counts as offline (3 intervals).
HEARTBEATS_LOST = 3
#: What a heartbeat says of alarms: heartbeats come only while the driver is not in alarm.
NO_ALARMS = common.AlarmFlags(0)

ROLES: dict[int, RoleOf] = {
    Reg.WORK_MODE: RoleOf(Role.MODE, lambda raw, _s: _MODE_OF.get(raw)),
    Reg.CONTROL_WORD: RoleOf(Role.ENABLE, lambda raw, _s: raw == codec.ControlWord.ENABLE),
    Reg.POSITION_MODE: RoleOf(
        Role.POSITION_MODE, lambda raw, _s: raw == codec.PositionMode.RELATIVE
    ),
    Reg.TARGET_POSITION: RoleOf(Role.POSITION),
    Reg.TARGET_SPEED: RoleOf(Role.SPEED),
    Reg.TARGET_TORQUE: RoleOf(Role.TORQUE),
    Reg.POSITION_RAMP: RoleOf(Role.POSITION_RAMP),
    Reg.SPEED_RAMP: RoleOf(Role.SPEED_RAMP),
    Reg.MAX_SPEED: RoleOf(Role.MAX_SPEED),
    Reg.ALARM_RESET: RoleOf(Role.ALARM_RESET),
    Reg.ORIGIN: RoleOf(Role.ONE_SHOT),
}

#: A register the ZLAC706 does not have: writing it gets the "no such register" reply.
PROBE_REGISTER = 0x7E


class Zlac706CanDriver(Zlac706Driver):
    """One ZLAC706 node on a CAN bus."""

    protocol: ClassVar[str] = "zlac706_can"
    broadcast_id: ClassVar[int | None] = codec.BROADCAST_ID
    frames = staticmethod(frames_for)
    roles: ClassVar[dict[int, RoleOf]] = ROLES
    #: The manual's limit is 500 ms; 100 ms of margin for a busy bus and the host.
    keepalive_period_s: ClassVar[float] = 0.4
    streams_positions: ClassVar[bool] = True

    def __init__(self, name: str, device_id: int, *, heartbeat_ms: int = 0, **options: Any) -> None:
        super().__init__(name, device_id, **options)
        self.heartbeat_s = heartbeat_ms / 1000
        self.last_heartbeat: float | None = None
        #: The heartbeat's halves taken since it was last news (rule 3).
        self._halves: set[type] = set()

    def poll(self) -> list[Request]:
        return []  # no read command: heartbeats only

    @classmethod
    def probe(cls, device_id: int) -> Request:
        """A write to a register the ZLAC706 does not have: answered ``FF`` (no such
        register), and it changes nothing."""
        return Request.of(codec, codec.Write(device_id, PROBE_REGISTER, 0))

    @classmethod
    def heartbeat_frames(cls, device_id: int) -> tuple[object, ...]:
        """The default heartbeat: position, then current and speed."""
        return (
            codec.HeartbeatPosition(device_id, 0),
            codec.HeartbeatCurrentSpeed(device_id, 0, 0),
        )

    def init(self) -> list[Request]:
        """Rule 4. The runner repeats ``init`` at the poll rate while the node is offline (with
        heartbeats expected, until the first one), so it never releases a motor that a client
        enabled since: the mode is written again, if known, and while the power stage is not
        known (the gateway's first word to it), 0 rpm, 0 A and a release, so that no speed or
        torque preset before the gateway came starts the motor at the next enable; even when
        the mode is known by then (a base sets its wheels' mode as they come online, which
        may be before their first ``init``)."""
        settings = self.machine.settings
        mode = (
            []
            if settings.mode is None
            else self._unchecked(schema.SetMode(op="set_mode", mode=settings.mode))
        )
        if settings.enabled is not None:
            return mode
        return [*mode, *self.nothing_preset(), *self._unchecked(schema.Disable(op="disable"))]

    def keepalive_request(self) -> Request:
        """The last speed written, again (``commanded_speed_raw``)."""
        speed = codec.Write(self.device_id, Reg.TARGET_SPEED, self.commanded_speed_raw)
        return Request.of(codec, speed, idempotent=True)

    def refreshes_keepalive(self, request: Request) -> bool:
        frame = request.frame
        return isinstance(frame, codec.Write) and frame.register == Reg.TARGET_SPEED

    def apply(self, request: Request, reply: tuple[object, ...], now: float) -> dict[str, Any]:
        answer = reply[0]
        if isinstance(answer, codec.WriteAck):
            self.acknowledged(request.frame)
        elif isinstance(answer, codec.NoSuchRegister):
            # Only a raw write can get here (``frames_for`` checks the table); nothing changed.
            self.machine.forget_pending()
            self.emit("rejected", register=int(answer.register), reason="no such register")
            raise DeviceRefusedError(
                f"node {self.device_id} has no register {answer.register:#04x}: the write was "
                "not taken",
                device=self.name,
                device_id=self.device_id,
            )
        return {}

    def unsolicited(self, event: object, now: float) -> bool:
        kind = type(event)
        handler = _UNSOLICITED.get(kind)
        if handler is None:
            return False  # a late echo: its write already counted as failed
        self.last_heartbeat = now
        if self.misses < OFFLINE_AFTER:  # rule 2: a heartbeat answers no write
            self.reported(now)
        handler(self, event, now)
        return self._news_with(kind)

    def begins_reading(self, event: object) -> bool:
        return type(event) in HEARTBEAT_HALVES and not self._halves

    def _news_with(self, kind: type) -> bool:
        """Whether the state is news with a frame of ``kind`` taken (rule 3)."""
        if kind not in HEARTBEAT_HALVES:
            return True
        if kind in self._halves:  # its other half was lost
            self._halves = {kind}
            return True
        self._halves.add(kind)
        if len(self._halves) < len(HEARTBEAT_HALVES):
            return False
        self._halves = set()
        return True

    def heard(self, now: float) -> None:
        if not self.heartbeat_s:
            super().heard(now)
            return
        # With heartbeats expected they alone bring the node online (rule 2).
        self.last_reply = now
        self.misses = 0

    def check_heartbeat(self, now: float) -> None:
        """Called by the runner: offline once ``HEARTBEATS_LOST`` intervals passed without one."""
        if not self.heartbeat_s or self.last_heartbeat is None:
            return
        if now - self.last_heartbeat > HEARTBEATS_LOST * self.heartbeat_s:
            self.went_offline("heartbeat lost")

    def has_measurements(self) -> bool:
        return self.last_heartbeat is not None

    def _take_position(self, event: codec.HeartbeatPosition, now: float) -> None:
        self.take_position(event.position_raw, now)
        self.take_alarms(NO_ALARMS)

    def _take_current_speed(self, event: codec.HeartbeatCurrentSpeed, now: float) -> None:
        self.measured["current_ma"] = round(event.current_a * 1000)
        self.measured["speed_rpm"] = event.speed_rpm
        self.take_alarms(NO_ALARMS)

    def _take_alarm_report(self, event: codec.AlarmReport, now: float) -> None:
        self.take_alarms(event.alarms)


#: The frames of one heartbeat (rule 3).
HEARTBEAT_HALVES = frozenset({codec.HeartbeatPosition, codec.HeartbeatCurrentSpeed})

_UNSOLICITED: dict[type, Callable[[Zlac706CanDriver, Any, float], None]] = {
    codec.HeartbeatPosition: Zlac706CanDriver._take_position,
    codec.HeartbeatCurrentSpeed: Zlac706CanDriver._take_current_speed,
    codec.AlarmReport: Zlac706CanDriver._take_alarm_report,
}
