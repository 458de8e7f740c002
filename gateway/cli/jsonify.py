"""Frames and events as plain JSON values, every field under its own (unit-bearing) name.

Enums become their names, flag sets lists of names, bytes lowercase hex, CAN frames cansend
text; a dataclass becomes an object whose ``"event"`` is its class name, except a register's
``Reading``, which is a value, not an event: its fields alone.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.registers import Reading


def to_jsonable(value: Any) -> Any:
    """Convert a codec frame or event (or anything inside one) to JSON-ready values.

    >>> to_jsonable(CanFrame(1, b"\\x00\\xfa"))
    '001#00fa'
    >>> to_jsonable(Reading("overtemp_limit", 98, 600, 60.0, "°C"))
    {'register': 'overtemp_limit', 'address': 98, 'raw': 600, 'value': 60.0, 'unit': '°C'}
    """
    if isinstance(value, CanFrame):
        return str(value)
    if isinstance(value, enum.Flag):
        return [member.name for member in type(value) if member in value and member.value]
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
        return fields if isinstance(value, Reading) else {"event": type(value).__name__, **fields}
    if isinstance(value, list | tuple):
        return [to_jsonable(item) for item in value]
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    return value
