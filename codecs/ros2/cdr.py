"""CDR as ROS 2 puts it on the wire (XCDR1, little-endian): a writer and a bounded reader.

Every ROS 2 middleware, rmw_zenoh included, serialises a message with Fast-CDR into classic
CDR behind a 4-byte encapsulation header; rosbags' ``serialize_cdr`` writes the same bytes.
This file knows the primitives, strings and counts; ``messages`` walks a type's fields.

Rules of this file:

1. The payload starts with ``CDR_LE`` (``00 01`` little-endian CDR, then two option bytes the
   reader ignores). Each primitive is aligned to its own size (1, 2, 4 or 8), counted from the
   end of that header; an array of primitives is aligned only when it holds an element, as
   Fast-CDR and rosbags do.
2. A string is a uint32 length that counts the NUL terminator, the UTF-8 bytes, then the NUL.
   A sequence is a uint32 count then its elements; a fixed array is its elements alone; a
   bool is one byte, 0 or 1.
3. The reader is bounded: every read checks the bytes left first, and a count that the bytes
   left cannot hold (at the element's smallest wire size) fails before anything is allocated.
   A wrong header, a string without its NUL or not UTF-8, a bool other than 0 or 1: each fails.
4. Failures of the reader raise ``CdrError``; ``messages.decode`` turns that into ``None``, so
   bytes from the network never raise out of the package. The writer raises ``EncodeError``.
5. Formats are compiled once (``struct.Struct``); an array of primitives is one struct call.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Final

from busgate.codecs.errors import CdrError, EncodeError

__all__ = [
    "CDR_LE",
    "HEADER_SIZE",
    "MAX_TRAILING_BYTES",
    "PRIMITIVE_SIZES",
    "CdrReader",
    "CdrWriter",
]

#: Encapsulation header of little-endian classic CDR (PLAIN_CDR_LE), options zero.
CDR_LE: Final = b"\x00\x01\x00\x00"
HEADER_SIZE: Final = len(CDR_LE)
#: Bytes a payload may carry after its last field: padding to a 4-byte boundary, which some
#: senders add. Their values are not checked (the same rule as rosbags' reader).
MAX_TRAILING_BYTES: Final = 3

#: struct format letter of each primitive, as a ``.msg`` spells it (``char`` is read as uint8
#: by ``definitions`` before it gets here).
_FORMATS: Final[dict[str, str]] = {
    "bool": "B",
    "byte": "B",
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}
_STRUCTS: Final[dict[str, struct.Struct]] = {
    kind: struct.Struct("<" + letter) for kind, letter in _FORMATS.items()
}
#: Wire size in bytes, which is also the alignment, of each primitive.
PRIMITIVE_SIZES: Final[dict[str, int]] = {kind: s.size for kind, s in _STRUCTS.items()}
_UINT32: Final = _STRUCTS["uint32"]
_NUL: Final = b"\x00"


def _array_format(kind: str, count: int) -> str:
    return f"<{count}{_FORMATS[kind]}"


def _check_bools(values: Sequence[object]) -> None:
    for value in values:
        if value is not True and value is not False:
            raise EncodeError(f"{value!r} is not a bool", value=value)


class CdrWriter:
    """Builds one payload: the header, then each value appended in field order."""

    def __init__(self) -> None:
        self._buf = bytearray(CDR_LE)

    def data(self) -> bytes:
        """The payload written so far, header included."""
        return bytes(self._buf)

    def _align(self, size: int) -> None:
        padding = -(len(self._buf) - HEADER_SIZE) % size
        if padding:
            self._buf += bytes(padding)

    def primitive(self, kind: str, value: object) -> None:
        """Append one primitive, aligned to its size."""
        if kind == "bool":
            _check_bools((value,))
        packer = _STRUCTS[kind]
        self._align(packer.size)
        try:
            self._buf += packer.pack(value)
        except (struct.error, OverflowError, TypeError) as error:
            raise EncodeError(f"{value!r} does not fit a {kind}: {error}", value=value) from error

    def primitives(self, kind: str, values: Sequence[object]) -> None:
        """Append the elements of an array of primitives (no count), in one struct call."""
        if not values:
            return
        if kind == "bool":
            _check_bools(values)
        self._align(PRIMITIVE_SIZES[kind])
        try:
            self._buf += struct.pack(_array_format(kind, len(values)), *values)
        except (struct.error, OverflowError, TypeError) as error:
            raise EncodeError(f"an element does not fit a {kind}: {error}") from error

    def count(self, count: int) -> None:
        """Append a sequence's element count (uint32)."""
        self.primitive("uint32", count)

    def string(self, value: str) -> None:
        """Append a string: its length with the NUL, its UTF-8 bytes, the NUL."""
        try:
            encoded = value.encode()
        except UnicodeEncodeError as error:
            raise EncodeError(f"{value!r} is not valid Unicode: {error}", value=value) from error
        self.count(len(encoded) + 1)
        self._buf += encoded + _NUL


class CdrReader:
    """Reads one payload front to back; every method raises ``CdrError`` on bad bytes."""

    def __init__(self, data: bytes | bytearray | memoryview, max_count: int | None = None) -> None:
        self._data = bytes(data)
        if self._data[:2] != CDR_LE[:2] or len(self._data) < HEADER_SIZE:
            raise CdrError("not a little-endian CDR payload")
        self._pos = HEADER_SIZE
        #: The longest sequence or string taken (``None``: as long as the bytes left hold).
        self._max_count = max_count

    @property
    def remaining(self) -> int:
        """Bytes not read yet."""
        return len(self._data) - self._pos

    def _align(self, size: int) -> None:
        self._pos += -(self._pos - HEADER_SIZE) % size

    def _take(self, size: int) -> int:
        """Claim ``size`` bytes; return where they start."""
        start = self._pos
        if size > len(self._data) - start:
            raise CdrError(f"{size} bytes needed at offset {start}, the payload ends first")
        self._pos = start + size
        return start

    def primitive(self, kind: str) -> object:
        """Read one primitive, aligned to its size."""
        unpacker = _STRUCTS[kind]
        self._align(unpacker.size)
        (value,) = unpacker.unpack_from(self._data, self._take(unpacker.size))
        if kind == "bool":
            return _as_bool(value)
        return value

    def primitives(self, kind: str, count: int) -> list[object]:
        """Read ``count`` primitives of an array (its count already read)."""
        if count == 0:
            return []
        size = PRIMITIVE_SIZES[kind]
        self._align(size)
        start = self._take(size * count)
        values = list(struct.unpack_from(_array_format(kind, count), self._data, start))
        if kind == "bool":
            return [_as_bool(value) for value in values]
        return values

    def count(self, element_min_bytes: int) -> int:
        """Read a sequence's count; fail if the bytes left cannot hold that many elements."""
        self._align(_UINT32.size)
        (count,) = _UINT32.unpack_from(self._data, self._take(_UINT32.size))
        if self._max_count is not None and count > self._max_count:
            raise CdrError(f"a count of {count}, over the {self._max_count} taken")
        if count * element_min_bytes > self.remaining:
            raise CdrError(f"a count of {count} does not fit the {self.remaining} bytes left")
        return count

    def string(self) -> str:
        """Read a string; a length of 0 is read as "" (Fast-CDR writes 1, accepts 0)."""
        length = self.count(1)
        if length == 0:
            return ""
        start = self._take(length)
        if self._data[start + length - 1] != 0:
            raise CdrError(f"a string at offset {start} lacks its NUL terminator")
        try:
            return self._data[start : start + length - 1].decode()
        except UnicodeDecodeError as error:
            raise CdrError(f"a string at offset {start} is not UTF-8") from error

    def finish(self) -> None:
        """Check that only padding is left after the last field."""
        if self.remaining > MAX_TRAILING_BYTES:
            raise CdrError(f"{self.remaining} bytes left after the last field")


def _as_bool(value: object) -> bool:
    if value not in (0, 1):
        raise CdrError(f"a bool byte of {value!r}")
    return value == 1
