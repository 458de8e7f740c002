"""DS servo driver: a ``busgate.schemas.ds_servo`` command becomes the codec frames that do it.

Every op is one frame. ``action`` and ``group_move`` always go to the broadcast id, whatever
``device_id`` says; the other ops go to ``device_id`` and the codec refuses the ones the
manual forbids to broadcast (ping, read, deferred move) when it encodes them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from busgate.codecs import ds_servo as codec
from busgate.schemas import ds_servo as schema

_TORQUE = codec.REGISTERS["torque_enable"].address
_SERVO_ID = codec.REGISTERS["servo_id"].address


def _move(command: schema.Move, device_id: int) -> codec.Frame:
    if command.deferred:
        return codec.RegWrite(device_id, command.position, command.time_ms)
    return codec.Write(
        device_id, codec.MOVE_ADDRESS, codec.move_data(command.position, command.time_ms)
    )


def _group_move(command: schema.GroupMove, device_id: int) -> codec.Frame:
    return codec.SyncWrite(
        tuple(codec.SyncTarget(t.id, t.position, t.time_ms) for t in command.targets)
    )


_FRAME_FOR: dict[type, Callable[[Any, int], codec.Frame]] = {
    schema.Ping: lambda c, device_id: codec.Ping(device_id),
    schema.Read: lambda c, device_id: codec.Read(device_id, c.address, c.length),
    schema.Write: lambda c, device_id: codec.Write(device_id, c.address, bytes.fromhex(c.data)),
    schema.Move: _move,
    schema.Action: lambda c, device_id: codec.Action(),
    schema.GroupMove: _group_move,
    schema.Torque: lambda c, device_id: codec.Write(device_id, _TORQUE, bytes([int(c.on)])),
    schema.SetId: lambda c, device_id: codec.Write(device_id, _SERVO_ID, bytes([c.new_id])),
    schema.GotoPreset: lambda c, device_id: codec.Write(
        device_id, codec.GOTO_PRESET_ADDRESSES[c.n - 1], b""
    ),
    schema.StorePreset: lambda c, device_id: codec.Write(
        device_id, codec.PRESET_ADDRESSES[c.n - 1], b""
    ),
    schema.Reset: lambda c, device_id: codec.Reset(device_id),
}


def frames_for(command: Any, device_id: int) -> list[codec.Frame]:
    """The frames, in order, that carry out ``command`` on servo ``device_id``.

    >>> from busgate.codecs.ds_servo import encode
    >>> move = schema.COMMAND_ADAPTER.validate_json('{"op":"move","position":2048,"time_ms":1000}')
    >>> [encode(f).hex(" ") for f in frames_for(move, 254)]   # manual 2.1
    ['ff ff fe 07 03 2a 08 00 03 e8 da']
    """
    return [_FRAME_FOR[type(command)](command, device_id)]
