"""A simulated ZLAC706 hub-motor servo driver behind either of its wire protocols.

One driver model (``zlac706_motor.Zlac706Motor``) and two front-ends that speak to it:
``Zlac706CanDevice`` (manual 8.1: ``FA`` writes on the node's identifier, ``DA`` to all on
identifier 0, heartbeats and alarm reports) and ``Zlac706Rs232Device`` (manual 8.2: 4-byte
writes acknowledged ``addr addr``, the monitor request answered by eight frames). Rules of
this file:

1. A front-end only maps its protocol's registers (the codec's ``REGISTERS`` and codes) to
   the model's settings and commands, through one dispatch table per protocol.
2. Every write to a register that exists is acknowledged (``FB``/``DB``, ``addr addr``),
   whether or not the driver acts on it: a position target before enable, a code the register
   does not know, a PC command under external control. Values past a register's range are
   clamped to it (hub motors: ±1000 rpm), as the driver's firmware limits them.
3. The keep-alive (feed-forward gain 1, speed mode): on CAN a target-speed write feeds it and
   the shaft locks 500 ms after the last; on RS232 only the monitor request ``80 00 80``
   feeds it, and the shaft locks 1 s after the last (manual 8.2.2).

Where the manual is silent, this file chooses (each choice is commented where it applies):
the heartbeat interval (100 ms) and the alarm reports' timing with heartbeats off, that
every node answers a broadcast, and what the external-pulse control mode does.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from typing import Any, Final

from busgate.codecs import zlac706_can as can_codec
from busgate.codecs import zlac706_rs232 as rs232_codec
from busgate.codecs.registers import Register, require_range
from busgate.codecs.timing import ProtocolTiming
from busgate.codecs.zlac706_common import AlarmFlags, Mode
from busgate.gateway.sim.zlac706_motor import FAULTS, Zlac706Motor

CAN_KEEPALIVE_S: Final = 0.5
RS232_KEEPALIVE_S: Final = 1.0
#: The heartbeat interval is set with the vendor tool (the manual's example: 500 ms, 0 = off).
#: We default to 100 ms: often enough to be the gateway's telemetry on CAN, where nothing can
#: be read, and a small share (two frames in 100 ms) of a 500 kbit/s bus.
DEFAULT_HEARTBEAT_MS: Final = 100
#: "If the driver alarms, it forces the alarm code up" (8.1.2 step 7): with heartbeats off we
#: still report an alarm, at the 1 s period of the manual's alarm log.
ALARM_REPORT_S: Final = 1.0


def _turnaround(timing: ProtocolTiming) -> tuple[float, float]:
    return timing.reply_min_s, timing.reply_max_s


def _clamp(register: Register, value: int) -> int:
    lo, hi = register.limits
    return max(lo, min(hi, value))


def _check_fault(name: str) -> AlarmFlags:
    try:
        return FAULTS[name]
    except KeyError:
        raise ValueError(
            f"a ZLAC706 has no fault {name!r}; it has {', '.join(sorted(FAULTS))}"
        ) from None


# A handler carries out one register write: ``handler(device, value, now)``.
Handler = Callable[[Any, int, float], None]


def _setting(codec: Any, address: int, name: str) -> Handler:
    """Store the value, clamped to the register's range, as the model's setting ``name``."""
    register = codec.REGISTERS.at(address)
    return lambda device, value, now: device.motor.store(name, _clamp(register, value), now)


def _ramp(name: str) -> Handler:
    # CAN carries a ramp in d2 (accel) and d3 (decel); d0 and d1 mean nothing.
    return lambda device, value, now: device.motor.store(name, value & 0xFFFF, now)


def _codes(actions: dict[int, Callable[[Zlac706Motor, float], None]]) -> Handler:
    """A coded register: each known code is a command; any other value does nothing."""

    def handle(device: Any, value: int, now: float) -> None:
        action = actions.get(value)
        if action is not None:
            action(device.motor, now)

    return handle


def _choice(name: str, values: dict[int, object]) -> Handler:
    """A coded register that selects a setting's value (work mode, position mode)."""

    def select(value: object) -> Callable[[Zlac706Motor, float], None]:
        return lambda motor, now: motor.store(name, value, now)

    return _codes({code: select(v) for code, v in values.items()})


class HeartbeatContent(enum.IntEnum):
    """The vendor tool's heartbeat choices (8.1.1 (6))."""

    POSITION_CURRENT_SPEED = 0
    POSITION = 1
    CURRENT_SPEED = 2


class Zlac706CanDevice:
    """A ZLAC706 on a CAN bus (``SimDevice``): node ``device_id`` (1–109), heartbeats every
    ``heartbeat_ms`` (0: none) with ``heartbeat_content`` (the manual's option 0, 1 or 2)."""

    turnaround_s = _turnaround(can_codec.TIMING)

    def __init__(
        self,
        device_id: int,
        *,
        heartbeat_ms: int = DEFAULT_HEARTBEAT_MS,
        heartbeat_content: int = HeartbeatContent.POSITION_CURRENT_SPEED,
    ) -> None:
        self.device_id = require_range("device_id", device_id, 1, can_codec.MAX_NODE_ID)
        if heartbeat_ms < 0:
            raise ValueError(f"heartbeat_ms must not be negative, not {heartbeat_ms}")
        self.heartbeat_s = heartbeat_ms / 1000
        self.heartbeat_content = HeartbeatContent(heartbeat_content)
        self.motor = Zlac706Motor(keepalive_s=CAN_KEEPALIVE_S)
        self._lock = threading.Lock()
        self._next_report: float | None = None  # None: report at the next chance (boot)

    def accepts(self, command: object) -> bool:
        return isinstance(command, can_codec.Write) and command.device_id in (
            self.device_id,
            can_codec.BROADCAST_ID,
        )

    def handle(self, command: can_codec.Write, now: float) -> list[object]:
        """Carry out the write and echo it (``FB``, ``DB`` for a broadcast), or answer ``FF``
        (``DF``) for a register the driver does not have.

        A broadcast is echoed by every node, as the manual describes: the host may see the
        same ``DB`` frame once per node, or fewer where identical frames merged on the bus.
        """
        handler = _CAN_WRITES.get(command.register)
        fields = (command.device_id, command.register, command.value, command.group)
        if handler is None:
            return [can_codec.NoSuchRegister(*fields)]
        with self._lock:
            self.motor.settle(now)
            handler(self, command.value, now)
        return [can_codec.WriteAck(*fields)]

    def spontaneous(self, now: float) -> list[object]:
        """Heartbeats every ``heartbeat_s``; while an alarm stands, alarm reports instead."""
        with self._lock:
            self.motor.settle(now)
            alarm = bool(self.motor.alarms)
            period = self.heartbeat_s or (ALARM_REPORT_S if alarm else 0.0)
            if not period:
                self._next_report = None
                return []
            if self._next_report is not None and now < self._next_report:
                return []
            # Never a burst to catch up: a late report moves the schedule on.
            due = (now if self._next_report is None else self._next_report) + period
            self._next_report = due if due > now else now + period
            if alarm:
                return [can_codec.AlarmReport(self.device_id, self.motor.status())]
            return [beat(self, now) for beat in _HEARTBEATS[self.heartbeat_content]]

    def reboot(self, now: float) -> None:
        with self._lock:
            self.motor.reset(now)
            self._next_report = None

    def inject_fault(self, fault: str, now: float) -> None:
        """Raise an alarm (``over_current``, ``over_voltage``, ``encoder``,
        ``over_temperature``, ``under_voltage``, ``overload``) until an alarm reset."""
        alarm = _check_fault(fault)
        with self._lock:
            self.motor.settle(now)
            self.motor.raise_fault(alarm, now)

    def _position_beat(self, now: float) -> can_codec.HeartbeatPosition:
        return can_codec.HeartbeatPosition(self.device_id, self.motor.feedback_position(now))

    def _current_speed_beat(self, now: float) -> can_codec.HeartbeatCurrentSpeed:
        return can_codec.HeartbeatCurrentSpeed(
            self.device_id, self.motor.current_raw(now), self.motor.speed_raw(now)
        )


_HEARTBEATS: dict[HeartbeatContent, tuple[Callable[[Zlac706CanDevice, float], object], ...]] = {
    HeartbeatContent.POSITION_CURRENT_SPEED: (
        Zlac706CanDevice._position_beat,
        Zlac706CanDevice._current_speed_beat,
    ),
    HeartbeatContent.POSITION: (Zlac706CanDevice._position_beat,),
    HeartbeatContent.CURRENT_SPEED: (Zlac706CanDevice._current_speed_beat,),
}


CanReg = can_codec.CanRegister
_store_target_speed = _setting(can_codec, CanReg.TARGET_SPEED, "target_speed")


def _can_speed(device: Zlac706CanDevice, value: int, now: float) -> None:
    device.motor.feed_keepalive(now)  # on CAN the speed command is the keep-alive
    _store_target_speed(device, value, now)


_CAN_WRITES: dict[int, Handler] = {
    CanReg.TARGET_TORQUE: _setting(can_codec, CanReg.TARGET_TORQUE, "target_torque"),
    CanReg.CONTROL_WORD: _codes(
        {
            can_codec.ControlWord.ENABLE: Zlac706Motor.enable,
            can_codec.ControlWord.RELEASE: Zlac706Motor.disable,
        }
    ),
    CanReg.TARGET_SPEED: _can_speed,
    CanReg.POSITION_RAMP: _ramp("position_ramp"),
    CanReg.SPEED_RAMP: _ramp("speed_ramp"),
    CanReg.MAX_SPEED: _setting(can_codec, CanReg.MAX_SPEED, "max_speed"),
    CanReg.ALARM_RESET: _codes({can_codec.AlarmReset.RESET: Zlac706Motor.reset_alarm}),
    CanReg.TARGET_POSITION: lambda device, value, now: device.motor.move_to(value, now),
    CanReg.POSITION_MODE: _choice(
        "relative", {can_codec.PositionMode.ABSOLUTE: False, can_codec.PositionMode.RELATIVE: True}
    ),
    CanReg.ORIGIN: _codes({can_codec.Origin.SEARCH: Zlac706Motor.search_origin}),
    CanReg.WORK_MODE: _choice(
        "mode",
        {
            can_codec.WorkMode.SPEED: Mode.VELOCITY,
            can_codec.WorkMode.POSITION: Mode.POSITION,
            can_codec.WorkMode.TORQUE: Mode.TORQUE,
        },
    ),
    **{
        register: _setting(can_codec, register, gain.value)
        for gain, register in can_codec.GAIN_REGISTERS.items()
    },
    CanReg.RATED_CURRENT: _setting(can_codec, CanReg.RATED_CURRENT, "rated_current"),
}


class Zlac706Rs232Device:
    """A ZLAC706 on its RS232 port (``SimDevice``). The link is point to point and frames
    carry no id: it takes every frame, and ``device_id`` is only a label (for silent ids)."""

    turnaround_s = _turnaround(rs232_codec.TIMING)

    def __init__(self, device_id: int = 1) -> None:
        self.device_id = device_id
        self.motor = Zlac706Motor(keepalive_s=RS232_KEEPALIVE_S)
        self._lock = threading.Lock()
        self._power_up()

    def accepts(self, command: object) -> bool:
        return True

    def handle(self, command: object, now: float) -> list[object]:
        """A write: carry it out and acknowledge it (``addr addr``). The monitor request:
        feed the keep-alive and answer with the eight monitor frames."""
        with self._lock:
            self.motor.settle(now)
            if isinstance(command, rs232_codec.MonitorRequest):
                self.motor.feed_keepalive(now)
                return self._monitor(now)
            assert isinstance(command, rs232_codec.Write)  # the only other host frame
            if not (self.external and command.register in _PC_COMMANDS):
                _RS232_WRITES[command.register](self, command.value, now)
            return [rs232_codec.Ack(command.register)]

    def spontaneous(self, now: float) -> list[object]:
        return []  # over RS232 the driver only answers

    def reboot(self, now: float) -> None:
        with self._lock:
            self.motor.reset(now)
            self._power_up()

    def inject_fault(self, fault: str, now: float) -> None:
        """Raise an alarm (as ``Zlac706CanDevice.inject_fault``); the status word shows it."""
        alarm = _check_fault(fault)
        with self._lock:
            self.motor.settle(now)
            self.motor.raise_fault(alarm, now)

    def _power_up(self) -> None:
        self.position_high = 0  # register 50, used by the next 05 write
        self.external = False  # control mode C0: position from external pulses

    def _status(self) -> AlarmFlags:
        external = AlarmFlags.EXTERNAL_CONTROL if self.external else AlarmFlags(0)
        return self.motor.status() | external

    def _monitor(self, now: float) -> list[object]:
        item = rs232_codec.MonitorItem
        motor = self.motor
        commanded = rs232_codec.split_position(motor.commanded_position(now))
        feedback = rs232_codec.split_position(motor.feedback_position(now))
        return [
            rs232_codec.StatusReport(self._status()),
            rs232_codec.BusVoltage(motor.bus_voltage_v()),
            rs232_codec.OutputCurrent(motor.current_raw(now)),
            rs232_codec.OutputSpeed(motor.speed_raw(now)),
            rs232_codec.PositionWord(item.COMMANDED_POSITION_HIGH, commanded[0]),
            rs232_codec.PositionWord(item.COMMANDED_POSITION_LOW, commanded[1]),
            rs232_codec.PositionWord(item.FEEDBACK_POSITION_HIGH, feedback[0]),
            rs232_codec.PositionWord(item.FEEDBACK_POSITION_LOW, feedback[1]),
        ]

    def _set_control(self, mode: Mode, external: bool, now: float) -> None:
        self.external = external
        self.motor.store("mode", mode, now)

    def _position_low(self, value: int, now: float) -> None:
        # Note (2)/(4): the high half is sent first; the low half completes the target.
        self.motor.move_to(rs232_codec.join_position(self.position_high, value), now)


def _rs232_mode(device: Zlac706Rs232Device, value: int, now: float) -> None:
    """Register 02. External pulses (C0): the position loop follows the pulse input, where
    nothing arrives in a simulation, so the shaft holds; the driver is not under PC control,
    so PC enables and targets are acknowledged and ignored, and the status word adds 80."""
    control = _RS232_MODES.get(value)
    if control is not None:
        device._set_control(*control, now)


Rs232Reg = rs232_codec.Rs232Register
_RS232_MODES: Final[dict[int, tuple[Mode, bool]]] = {
    rs232_codec.ControlMode.PC_SPEED: (Mode.VELOCITY, False),
    rs232_codec.ControlMode.PC_POSITION: (Mode.POSITION, False),
    rs232_codec.ControlMode.PC_TORQUE: (Mode.TORQUE, False),
    rs232_codec.ControlMode.EXTERNAL_PULSES: (Mode.POSITION, True),
}
#: "PC 控制模式有效": what only works under PC control.
_PC_COMMANDS: Final = frozenset(
    {Rs232Reg.ENABLE, Rs232Reg.POSITION_LOW, Rs232Reg.SPEED, Rs232Reg.TORQUE, Rs232Reg.ORIGIN}
)
_RS232_WRITES: dict[int, Handler] = {
    Rs232Reg.ENABLE: _codes(
        {
            rs232_codec.EnableCode.ENABLE: Zlac706Motor.enable,
            rs232_codec.EnableCode.DISABLE: Zlac706Motor.disable,
        }
    ),
    Rs232Reg.MODE: _rs232_mode,
    Rs232Reg.POSITION_HIGH: lambda device, value, now: setattr(device, "position_high", value),
    Rs232Reg.POSITION_LOW: Zlac706Rs232Device._position_low,
    Rs232Reg.SPEED: _setting(rs232_codec, Rs232Reg.SPEED, "target_speed"),
    Rs232Reg.TORQUE: _setting(rs232_codec, Rs232Reg.TORQUE, "target_torque"),
    Rs232Reg.POSITION_RAMP: _ramp("position_ramp"),
    Rs232Reg.SPEED_RAMP: _ramp("speed_ramp"),
    Rs232Reg.SPEED_LIMIT: _setting(rs232_codec, Rs232Reg.SPEED_LIMIT, "max_speed"),
    Rs232Reg.RATED_CURRENT: _setting(rs232_codec, Rs232Reg.RATED_CURRENT, "rated_current"),
    Rs232Reg.CLEAR_FAULT: lambda device, value, now: device.motor.reset_alarm(now),
    Rs232Reg.POSITION_MODE: _choice(
        "relative",
        {rs232_codec.PositionMode.ABSOLUTE: False, rs232_codec.PositionMode.RELATIVE: True},
    ),
    Rs232Reg.ORIGIN: lambda device, value, now: device.motor.search_origin(now),
    **{
        register: _setting(rs232_codec, register, gain.value)
        for gain, register in rs232_codec.GAIN_REGISTERS.items()
    },
}
