"""ZLAC706 RS232 driver: a ``busgate.schemas.zlac706`` command becomes the RS232 frames that do it.

The link is point to point, so ``device_id`` is ignored (the CLI refuses ``--id``). Every op
is one frame except ``move``: a 32-bit position goes as its high 16 bits (register 50), then
its low 16 bits (register 05), in that order (manual 8.2.1 note 4). Speeds truncate toward
zero like the manual's speed table; the position-mode speed limit rounds (note 8: 60 rpm →
0x00A4). RS232 has no current-loop gains: ``set_gain`` of ``current_kp``/``current_kd`` is
refused here. Values wider than 16 bits are refused by the codec's encoder.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from busgate.codecs import zlac706_common as common
from busgate.codecs import zlac706_rs232 as codec
from busgate.codecs.errors import CommandError
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
