"""ZLAC706 CAN driver: a ``busgate.schemas.zlac706`` command becomes the CAN frames that do it.

Every op is one register write to ``device_id`` (0 writes to every node with ``DA``). Unit
conversions are the shared ones (``busgate.codecs.zlac706_common``): speeds truncate toward
zero, as the manual's 1000 rpm → 0x0AAA does for the speed target and the trapezoid speed
alike. The order a mode needs (mode, ramps, enable, then target: a position target sent
before enable is ignored) and the speed keep-alive are the gateway's state machine, not this
stateless mapping. ``monitor`` exists on RS232 only: on CAN the driver's heartbeat reports
position, current and speed unasked.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from busgate.codecs import zlac706_can as codec
from busgate.codecs import zlac706_common as common
from busgate.codecs.errors import CommandError
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


_FRAME_OF: dict[type, Callable[[Any, int], codec.Write]] = {
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
    return [_FRAME_OF[type(command)](command, device_id)]
