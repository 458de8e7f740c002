"""Encoding and decoding ROS 2 messages by type name, between plain values and CDR payloads.

A message is a dict of its fields: a Time is ``{"sec": 1, "nanosec": 2}``, a ``float64[]`` a
list of floats, a nested message a dict, a ``byte`` or ``char`` a small int. Each type's
codec is built once from ``definitions`` and walks the fields in wire order.

Rules of this file:

1. ``decode`` never raises on bytes: anything malformed is ``None``, including a payload with
   more than ``cdr.MAX_TRAILING_BYTES`` bytes after its last field. Up to that many trailing
   bytes, whatever their value, are padding and accepted (the same rule as rosbags' reader).
   A sequence longer than its bound, a bool byte other than 0 or 1: ``None`` too.
2. ``encode`` writes the encapsulation header then the fields. A missing field takes its zero
   value (0, 0.0, False, "", [], a nested zero, a fixed array of zeros), not the ``.msg``
   default value. A value of the wrong shape (an unknown field, a string where a number goes,
   an array of the wrong size, an int out of its range) raises ``EncodeError`` naming the
   field's path (``header.stamp.sec``, ``name[2]``; an array of numbers is named whole).
3. An unknown type name is a programming error: ``ValueError``, not ``KeyError``.
4. Numbers are checked by ``struct``, as it packs them: an int for a float field is fine, a
   bool field takes only ``True`` or ``False``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from busgate.codecs.errors import CdrError, EncodeError
from busgate.codecs.ros2.cdr import PRIMITIVE_SIZES, CdrReader, CdrWriter
from busgate.codecs.ros2.definitions import Collection, FieldType, Struct, struct

__all__ = ["MessageType", "decode", "encode", "message_type", "seconds_of", "time_of"]

#: The smallest wire size of a string: its uint32 length (Fast-CDR reads a length of 0 as "").
_STRING_MIN_BYTES = 4


@dataclass(frozen=True, slots=True)
class MessageType:
    """A type busgate speaks: ``name`` as ROS spells it, ``dds_name`` as the keys spell it."""

    name: str
    definition: Struct

    @property
    def dds_name(self) -> str:
        """``sensor_msgs::msg::dds_::JointState_`` for ``sensor_msgs/msg/JointState``."""
        package, kind, type_name = self.name.split("/")
        return f"{package}::{kind}::dds_::{type_name}_"


def message_type(name: str) -> MessageType:
    """The type called ``name`` (``sensor_msgs/msg/JointState``); ``ValueError`` if unknown."""
    return MessageType(name, struct(name))


def encode(name: str, value: Mapping[str, object]) -> bytes:
    """The CDR payload of ``value``, header included (rule 2).

    >>> encode("std_msgs/msg/Bool", {"data": True}).hex()
    '0001000001'
    """
    writer = CdrWriter()
    _codec(name).write(writer, value, "")
    return writer.data()


def time_of(seconds: float) -> dict[str, int]:
    """A ``builtin_interfaces/Time`` (or ``Duration``) of ``seconds``.

    >>> time_of(1.25)
    {'sec': 1, 'nanosec': 250000000}
    """
    nanoseconds = int(seconds * 1e9)
    return {"sec": nanoseconds // 1_000_000_000, "nanosec": nanoseconds % 1_000_000_000}


def seconds_of(time: Mapping[str, Any]) -> float:
    """The seconds of a decoded ``builtin_interfaces/Time`` or ``Duration`` (``time_of``'s
    inverse).

    >>> seconds_of({"sec": 1, "nanosec": 250000000})
    1.25
    """
    return time.get("sec", 0) + time.get("nanosec", 0) / 1e9


def decode(
    name: str, data: bytes | bytearray | memoryview, *, max_count: int | None = None
) -> dict[str, Any] | None:
    """The message in ``data``, or ``None`` when it is not a valid payload of ``name`` (or
    holds a sequence or string longer than ``max_count``: refused as it is read, before the
    rest is)."""
    codec = _codec(name)
    try:
        reader = CdrReader(data, max_count)
        value = codec.read(reader)
        reader.finish()
    except CdrError:
        return None
    return value


class _Codec(Protocol):
    """How one field's value goes to and comes from the wire."""

    min_bytes: int

    def zero(self) -> Any: ...

    def write(self, writer: CdrWriter, value: object, path: str) -> None: ...

    def read(self, reader: CdrReader) -> Any: ...


def _refuse(path: str, value: object, why: str) -> EncodeError:
    return EncodeError(f"{path or 'the message'}: {why}", field=path, value=value)


class _Primitive:
    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.min_bytes = PRIMITIVE_SIZES[kind]
        self._zero: object = {"bool": False, "float32": 0.0, "float64": 0.0}.get(kind, 0)

    def zero(self) -> object:
        return self._zero

    def write(self, writer: CdrWriter, value: object, path: str) -> None:
        try:
            writer.primitive(self.kind, value)
        except EncodeError as error:
            raise _refuse(path, value, str(error)) from error

    def read(self, reader: CdrReader) -> object:
        return reader.primitive(self.kind)


class _String:
    min_bytes = _STRING_MIN_BYTES

    def __init__(self, bound_bytes: int) -> None:
        self._bound_bytes = bound_bytes

    def zero(self) -> str:
        return ""

    def write(self, writer: CdrWriter, value: object, path: str) -> None:
        if not isinstance(value, str):
            raise _refuse(path, value, f"{value!r} is not a string")
        if self._bound_bytes and len(value.encode(errors="replace")) > self._bound_bytes:
            raise _refuse(path, value, f"longer than its bound of {self._bound_bytes} bytes")
        try:
            writer.string(value)
        except EncodeError as error:
            raise _refuse(path, value, str(error)) from error

    def read(self, reader: CdrReader) -> str:
        value = reader.string()
        if self._bound_bytes and len(value.encode()) > self._bound_bytes:
            raise CdrError(f"a string longer than its bound of {self._bound_bytes} bytes")
        return value


class _Array:
    """A fixed array (``size``), a bounded sequence (``bound``) or an unbounded one."""

    def __init__(self, element: _Codec, field_type: FieldType) -> None:
        self._element = element
        fixed = field_type.collection is Collection.FIXED
        self._size = field_type.capacity if fixed else 0
        self._bound = field_type.capacity if not fixed else 0
        self._kind = element.kind if isinstance(element, _Primitive) else ""
        self.min_bytes = element.min_bytes * self._size if fixed else PRIMITIVE_SIZES["uint32"]

    def zero(self) -> list[object]:
        return [self._element.zero() for _ in range(self._size)]

    def write(self, writer: CdrWriter, value: object, path: str) -> None:
        if not isinstance(value, Sequence) or isinstance(value, str | bytes):
            raise _refuse(path, value, f"{value!r} is not a list")
        if self._size and len(value) != self._size:
            raise _refuse(path, value, f"{len(value)} elements, not {self._size}")
        if self._bound and len(value) > self._bound:
            raise _refuse(path, value, f"{len(value)} elements, more than {self._bound}")
        if not self._size:
            writer.count(len(value))
        if self._kind:
            try:
                writer.primitives(self._kind, value)
            except EncodeError as error:
                raise _refuse(path, value, str(error)) from error
            return
        for index, element in enumerate(value):
            self._element.write(writer, element, f"{path}[{index}]")

    def read(self, reader: CdrReader) -> list[Any]:
        count = self._size or reader.count(self._element.min_bytes)
        if self._bound and count > self._bound:
            raise CdrError(f"{count} elements in a sequence bounded to {self._bound}")
        if self._kind:
            return reader.primitives(self._kind, count)
        return [self._element.read(reader) for _ in range(count)]


class _Struct:
    def __init__(self, fields: tuple[tuple[str, _Codec], ...]) -> None:
        self._fields = fields
        self._names = frozenset(name for name, _ in fields)
        self.min_bytes = sum(codec.min_bytes for _, codec in fields)

    def zero(self) -> dict[str, Any]:
        return {name: codec.zero() for name, codec in self._fields}

    def write(self, writer: CdrWriter, value: object, path: str) -> None:
        if not isinstance(value, Mapping):
            raise _refuse(path, value, f"{value!r} is not a dict")
        unknown = set(value) - self._names
        if unknown:
            raise _refuse(path, value, f"unknown fields {sorted(map(str, unknown))}")
        prefix = f"{path}." if path else ""
        for name, codec in self._fields:
            field_value = value[name] if name in value else codec.zero()
            codec.write(writer, field_value, prefix + name)

    def read(self, reader: CdrReader) -> dict[str, Any]:
        return {name: codec.read(reader) for name, codec in self._fields}


@functools.cache
def _codec(name: str) -> _Struct:
    return _Struct(tuple((field.name, _field_codec(field.type)) for field in struct(name).fields))


def _field_codec(field_type: FieldType) -> _Codec:
    element: _Codec
    if field_type.nested:
        element = _codec(field_type.element)
    elif field_type.element == "string":
        element = _String(field_type.string_capacity)
    else:
        element = _Primitive(field_type.element)
    if field_type.collection is Collection.SINGLE:
        return element
    return _Array(element, field_type)
