"""What every codec shares: the decoder events, the reply expectation and the stream decoder.

Rules of this file (and of every decoder built on it):

1. Bytes off a wire never raise. Noise, half frames after a reconnect and bad checksums are
   normal on a serial line, so they become events: ``Discarded`` for bytes that are not part
   of any frame, ``ChecksumMismatch`` for a well-delimited frame whose checksum fails.
2. ``feed()`` only buffers; ``next_event()`` returns one event or ``NEED_DATA``; ``events()``
   drains. Nothing is decoded behind the caller's back. A message decoder's ``decode()`` does
   both at once for one whole message, returning its one event (the queue left untouched).
3. Linear time: the scan position only moves forward; header search runs in C (``find``) and a
   run of garbage is reported as one ``Discarded`` event, not one per byte.
4. Bounded memory: once ``NEED_DATA`` is returned, what is kept is a possible frame prefix,
   shorter than the protocol's largest frame (``max_frame``).
5. On a bad checksum the decoder drops one byte past the header start and rescans, since a
   good frame can start inside a bad one.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final, Generic, TypeVar

__all__ = [
    "NEED_DATA",
    "ChecksumMismatch",
    "Discarded",
    "ExpectedReply",
    "HeaderFramedDecoder",
    "MessageDecoder",
    "NeedData",
    "StreamDecoder",
    "sum8",
]


class NeedData:
    """Type of the ``NEED_DATA`` sentinel: the decoder needs more bytes to say anything."""

    _instance: NeedData | None = None

    def __new__(cls) -> NeedData:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData()


@dataclass(frozen=True, slots=True)
class Discarded:
    """Bytes (or a CAN frame's bytes) that belong to no valid frame, and why."""

    data: bytes
    reason: str


@dataclass(frozen=True, slots=True)
class ChecksumMismatch:
    """A frame that was delimited correctly but failed its checksum."""

    frame: bytes
    expected: int
    received: int


@dataclass(frozen=True, slots=True)
class ExpectedReply:
    """What a bus owner should wait for after sending a command.

    ``wire_bytes`` is the largest size the reply can have on the wire (for CAN: data bytes per
    frame), so a deadline can be computed from wire time; ``frames`` how many frames make the
    reply; ``kinds`` the event classes that can answer; ``source_id`` who answers; ``echo``
    the fields (name, value) an answer that echoes its command carries, so that an echo of
    another command (a late answer to one that timed out) is not taken for this one's.
    """

    source_id: int | None  # None: a point-to-point link whose frames carry no id
    wire_bytes: int
    kinds: tuple[type, ...]
    frames: int = 1
    echo: tuple[tuple[str, object], ...] = ()

    def matches(self, event: object) -> bool:
        """True when ``event`` is (part of) the answer to the command this was made for."""
        if not isinstance(event, self.kinds) or getattr(event, "device_id", None) != self.source_id:
            return False
        return all(getattr(event, name, None) == value for name, value in self.echo)


def sum8(data: bytes | bytearray | memoryview) -> int:
    """Low 8 bits of the sum of ``data``.

    >>> hex(sum8(bytes.fromhex("0403 2137e803")))
    '0x4a'
    """
    return sum(data) & 0xFF


Event = TypeVar("Event")


class StreamDecoder(Generic[Event]):
    """Incremental decoder for a byte stream; subclasses say how one step of parsing goes.

    A subclass implements ``_step(buf, pos)``, which looks at the bytes from ``pos`` on and
    returns ``(event, new_pos)``, or ``(None, pos)`` when it needs more bytes.
    """

    #: The largest frame of the protocol; the buffer never keeps more once drained.
    max_frame: int = 256

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos = 0

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Buffer ``data``; decoding happens in ``next_event``."""
        self._buf += data

    @property
    def pending(self) -> int:
        """Bytes buffered and not yet turned into events."""
        return len(self._buf) - self._pos

    def next_event(self) -> Event | Discarded | ChecksumMismatch | NeedData:
        """Return the next event, or ``NEED_DATA`` when the buffer holds no complete one."""
        if self._pos < len(self._buf):
            event, new_pos = self._step(self._buf, self._pos)
            if event is not None:
                self._pos = new_pos
                return event
        del self._buf[: self._pos]
        self._pos = 0
        return NEED_DATA

    def events(self) -> Iterator[Event | Discarded | ChecksumMismatch]:
        """Yield every event the buffered bytes make, then stop."""
        while not isinstance(event := self.next_event(), NeedData):
            yield event

    def _step(
        self, buf: bytearray, pos: int
    ) -> tuple[Event | Discarded | ChecksumMismatch | None, int]:
        raise NotImplementedError


class HeaderFramedDecoder(StreamDecoder[Event]):
    """A stream of frames that start with a fixed header and carry their own length.

    Subclasses set ``header`` and implement ``_frame_size`` (from the header fields, before the
    body arrives), ``_checksum`` and ``_decode`` (a checked frame to an event; an unknown but
    well-formed frame becomes ``Discarded``).
    """

    header: bytes = b""

    def _frame_size(self, buf: bytearray, start: int) -> int | str | None:
        """Whole frame size from the header fields at ``start``; ``None`` when more bytes are
        needed to tell; a string (the reason) when the header fields are impossible."""
        raise NotImplementedError

    def _checksum(self, frame: bytes) -> int:
        raise NotImplementedError

    def _decode(self, frame: bytes) -> Event | Discarded:
        raise NotImplementedError

    def _step(
        self, buf: bytearray, pos: int
    ) -> tuple[Event | Discarded | ChecksumMismatch | None, int]:
        start = buf.find(self.header, pos)
        if start < 0:
            return self._skip_to_end(buf, pos)
        if start > pos:
            return Discarded(bytes(buf[pos:start]), "no frame header"), start
        size = self._frame_size(buf, start)
        if size is None or (isinstance(size, int) and len(buf) - start < size):
            return None, pos
        if isinstance(size, str):
            return Discarded(bytes(buf[start : start + 1]), size), start + 1
        frame = bytes(buf[start : start + size])
        expected = self._checksum(frame)
        if expected != frame[-1]:
            return ChecksumMismatch(frame, expected, frame[-1]), start + 1
        return self._decode(frame), start + size

    def _skip_to_end(self, buf: bytearray, pos: int) -> tuple[Discarded | None, int]:
        """No header from ``pos`` on: discard all but a trailing partial header."""
        end = len(buf)
        for keep in range(len(self.header) - 1, 0, -1):
            if buf.endswith(self.header[:keep]):
                end -= keep
                break
        if end > pos:
            return Discarded(bytes(buf[pos:end]), "no frame header"), end
        return None, pos


Message = TypeVar("Message")


class MessageDecoder(Generic[Message, Event]):
    """Incremental decoder for a transport that delivers whole messages (CAN frames).

    The same ``feed`` / ``next_event`` / ``events`` interface as ``StreamDecoder``; subclasses
    implement ``_decode(message)``, which never raises. ``max_pending`` bounds the queue: when
    the caller feeds more than it drains, the oldest messages are dropped and reported as one
    ``Discarded`` event.
    """

    max_pending: int = 1024

    def __init__(self) -> None:
        self._queue: deque[Message] = deque()
        self._dropped = 0

    def feed(self, message: Message) -> None:
        """Queue ``message``; decoding happens in ``next_event``."""
        if len(self._queue) >= self.max_pending:
            self._queue.popleft()
            self._dropped += 1
        self._queue.append(message)

    @property
    def pending(self) -> int:
        """Messages queued and not yet turned into events."""
        return len(self._queue)

    def next_event(self) -> Event | Discarded | NeedData:
        """Return the next event, or ``NEED_DATA`` when no message is queued."""
        if self._dropped:
            dropped, self._dropped = self._dropped, 0
            return Discarded(b"", f"{dropped} frames dropped: decoder queue full")
        if not self._queue:
            return NEED_DATA
        return self._decode(self._queue.popleft())

    def events(self) -> Iterator[Event | Discarded]:
        """Yield every event the queued messages make, then stop."""
        while not isinstance(event := self.next_event(), NeedData):
            yield event

    def decode(self, message: Message) -> Event | Discarded:
        """The event ``message`` makes, decoded now (the queue is neither used nor touched):
        what ``feed`` then ``next_event`` give on an empty queue, without their bookkeeping."""
        return self._decode(message)

    def _decode(self, message: Message) -> Event | Discarded:
        raise NotImplementedError
