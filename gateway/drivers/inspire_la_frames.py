"""Inspire LA commands as frames: a ``busgate.schemas.inspire_la`` command becomes the codec
frames that do it (``frames_for``, stateless), and each frame says what it does to the
actuators it addresses (``frame_effect``, by which the gateway authorises it) and the position
targets it sets on them (``frame_setpoints``, by which the gateway keeps each joint's limits).

Every op is one frame. ``group_move`` and ``group_follow`` always go to the broadcast id 255,
whatever ``device_id`` says. The ``set_*`` ops and ``zero_force`` write one whole register of
the control table, checked against the table's absolute bounds only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeGuard

from busgate.codecs import inspire_la as codec
from busgate.gateway.drivers.base import Effect, IdChange, Setpoint
from busgate.schemas import inspire_la as schema

#: The force-sensor zero register takes exactly this value ("settable range 1").
_ZERO_FORCE = codec.REGISTERS[codec.FORCE_ZERO].limits[0]


def _control(code: codec.ControlCode) -> Callable[[Any, int], codec.Frame]:
    return lambda command, device_id: codec.ControlCommand(device_id, code)


def _targets(command: schema.GroupMove | schema.GroupFollow) -> tuple[codec.Target, ...]:
    return tuple(codec.Target(t.id, t.position) for t in command.targets)


def _write_register(name: str, field: str) -> Callable[[Any, int], codec.Frame]:
    return lambda c, device_id: codec.register_write(device_id, name, getattr(c, field))


def _write_temperature(name: str) -> Callable[[Any, int], codec.Frame]:
    return lambda c, device_id: codec.register_write(
        device_id, name, codec.temperature_raw(c.temp_c)
    )


_FRAME_FOR: dict[type, Callable[[Any, int], codec.Frame]] = {
    schema.Move: lambda c, device_id: codec.MoveCommand(device_id, c.position, c.reply),
    schema.Follow: lambda c, device_id: codec.FollowCommand(device_id, c.position, c.reply),
    schema.Enable: _control(codec.ControlCode.ENABLE),
    schema.Estop: _control(codec.ControlCode.ESTOP),
    schema.Pause: _control(codec.ControlCode.PAUSE),
    schema.Save: _control(codec.ControlCode.SAVE),
    schema.Status: _control(codec.ControlCode.STATUS),
    schema.ClearFault: _control(codec.ControlCode.CLEAR_FAULT),
    schema.Read: lambda c, device_id: codec.ReadCommand(device_id, c.index, c.length),
    schema.Write: lambda c, device_id: codec.WriteCommand(
        device_id, c.index, bytes.fromhex(c.data)
    ),
    schema.SetId: _write_register(codec.ID, "new_id"),
    schema.SetOvercurrent: _write_register(codec.OVERCURRENT_LIMIT, "current_ma"),
    schema.SetOvertemp: _write_temperature(codec.OVERTEMP_LIMIT),
    schema.SetRewarm: _write_temperature(codec.REWARM_TEMPERATURE),
    schema.SetBaudrate: lambda c, device_id: codec.register_write(
        device_id, codec.BAUD_CODE, codec.baud_code(c.baudrate)
    ),
    schema.ZeroForce: lambda c, device_id: codec.register_write(
        device_id, codec.FORCE_ZERO, _ZERO_FORCE
    ),
    schema.GroupMove: lambda c, device_id: codec.GroupMoveCommand(_targets(c)),
    schema.GroupFollow: lambda c, device_id: codec.GroupFollowCommand(_targets(c)),
}


def frames_for(command: Any, device_id: int) -> list[codec.Frame]:
    """The frames, in order, that carry out ``command`` on actuator ``device_id``.

    >>> from busgate.codecs.inspire_la import encode
    >>> move = schema.COMMAND_ADAPTER.validate_json('{"op":"move","position":1000}')
    >>> [encode(f).hex() for f in frames_for(move, 3)]  # manual 3.7.2
    ['55aa04032137e8034a']
    """
    return [_FRAME_FOR[type(command)](command, device_id)]


_CONTROL_EFFECTS: dict[codec.ControlCode, Effect] = {
    codec.ControlCode.STATUS: Effect.READ,
    codec.ControlCode.ESTOP: Effect.STOP,
    codec.ControlCode.PAUSE: Effect.STOP,
}
_MOTION_FRAMES = (
    codec.MoveCommand,
    codec.FollowCommand,
    codec.GroupMoveCommand,
    codec.GroupFollowCommand,
)


def frame_effect(frame: codec.Frame) -> Effect:
    """What ``frame`` does: a target (or a raw write of the target register) moves; a status
    query or a read only asks; e-stop and pause stop; anything else changes a setting."""
    if isinstance(frame, _MOTION_FRAMES):
        return Effect.MOTION
    if isinstance(frame, codec.ReadCommand):
        return Effect.READ
    if isinstance(frame, codec.ControlCommand):
        return _CONTROL_EFFECTS.get(frame.code, Effect.SETTING)
    if _writes_target(frame):
        return Effect.MOTION
    return Effect.SETTING


def _writes_target(frame: codec.Frame) -> TypeGuard[codec.WriteCommand]:
    """Whether ``frame`` is a raw write reaching the target-position register."""
    return isinstance(frame, codec.WriteCommand) and codec.TARGET_POSITION in (
        codec.REGISTERS.touched(frame.index, len(frame.data))
    )


def frame_id_changes(frame: codec.Frame) -> list[IdChange]:
    """The id a raw write of the id register (``set_id`` is one) gives the device."""
    if isinstance(frame, codec.WriteCommand):
        new_id = codec.register_values(frame.index, frame.data).get(codec.ID)
        if new_id is not None:
            return [IdChange(frame.device_id, new_id)]
    return []


def frame_setpoints(frame: codec.Frame) -> list[Setpoint]:
    """The position targets ``frame`` sets, raw: a move's or a follow target, each target of
    a group frame under its own id, and a raw write's value of the target register (``None``
    when it writes one byte of it: the other byte is the device's, not known here)."""
    if isinstance(frame, codec.MoveCommand | codec.FollowCommand):
        return [Setpoint(frame.device_id, "position", frame.position_raw)]
    if isinstance(frame, codec.GroupMoveCommand | codec.GroupFollowCommand):
        return [Setpoint(t.device_id, "position", t.position_raw) for t in frame.targets]
    if _writes_target(frame):
        written = codec.register_values(frame.index, frame.data).get(codec.TARGET_POSITION)
        return [Setpoint(frame.device_id, "position", written)]
    return []
