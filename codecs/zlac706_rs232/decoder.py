"""Bytes to ZLAC706 RS232 frames, for both ends of the serial line.

The stream has no header and no length: a frame is known by its first byte. The host sends
4-byte writes (the first byte a writable register) and the 3-byte monitor request
``80 00 80``; the driver sends 2-byte acks ``X X`` (X a writable register) and 4-byte monitor
frames (the first byte a monitor item: 80, E1, E2, E4, E6–E9). The two address sets are
disjoint (``REGISTERS`` holds each address once), so every first byte says what follows.

Each decoder keeps a table first byte → frame size and scans: an unknown first byte starts a
run of ``Discarded`` bytes up to the next known one; a known one waits for its frame, checks
it (the sum byte; for an ack, the repeated address stands in for the checksum) and on a
mismatch reports ``ChecksumMismatch`` and rescans one byte on, as a good frame can start
inside a bad one. Noise can still fake a frame (``00 00`` is an ack of register 00): with
no header and at best one check byte the protocol cannot do better.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import partial
from typing import ClassVar, Final, TypeVar

from busgate.codecs.framing import ChecksumMismatch, Discarded, StreamDecoder, sum8
from busgate.codecs.zlac706_common import AlarmFlags, named
from busgate.codecs.zlac706_rs232.frames import (
    ACK_SIZE,
    FRAME_SIZE,
    MONITOR_REQUEST,
    Ack,
    BusVoltage,
    Command,
    MonitorRequest,
    OutputCurrent,
    OutputSpeed,
    PositionWord,
    Reply,
    StatusReport,
    Write,
)
from busgate.codecs.zlac706_rs232.registers import (
    CODES,
    MONITOR,
    POSITION_ITEMS,
    REGISTERS,
    WRITABLE,
    MonitorItem,
    Rs232Register,
)

MONITOR_REQUEST_ADDRESS: Final = MONITOR_REQUEST[0]


def _word(frame: bytes) -> int:
    """The frame's 16-bit value, signed or not as its register says."""
    return int.from_bytes(frame[1:3], "big", signed=REGISTERS.at(frame[0]).signed)  # type: ignore[union-attr]


Event = TypeVar("Event")


class _FirstByteFramed(StreamDecoder[Event]):
    """A stream whose frames are known by their first byte (see the module docstring)."""

    max_frame = FRAME_SIZE
    #: First byte → frame size.
    sizes: ClassVar[dict[int, int]] = {}
    _known: ClassVar[re.Pattern[bytes]]

    def __init_subclass__(cls) -> None:
        known = b"".join(re.escape(bytes([b])) for b in sorted(cls.sizes))
        cls._known = re.compile(b"[" + known + b"]")

    def _step(
        self, buf: bytearray, pos: int
    ) -> tuple[Event | Discarded | ChecksumMismatch | None, int]:
        size = self.sizes.get(buf[pos])
        if size is None:
            found = self._known.search(buf, pos + 1)
            end = len(buf) if found is None else found.start()
            return Discarded(bytes(buf[pos:end]), "no known address"), end
        if len(buf) - pos < size:
            return None, pos
        frame = bytes(buf[pos : pos + size])
        expected = self._check_byte(frame)
        if expected != frame[-1]:
            return ChecksumMismatch(frame, expected, frame[-1]), pos + 1
        event = self._decode(frame)
        # A frame refused by what it carries, not its check byte, is left after its first
        # byte (its ``Discarded`` holds that byte): the next frame may begin inside it.
        return event, pos + (len(event.data) if isinstance(event, Discarded) else size)

    def _check_byte(self, frame: bytes) -> int:
        return sum8(frame[:-1])

    def _decode(self, frame: bytes) -> Event | Discarded:
        """A checked frame to its event, or its first byte ``Discarded``; each subclass
        defines it."""
        raise NotImplementedError


class CommandDecoder(_FirstByteFramed[Command]):
    """Decodes the host's frames, as the driver sees them.

    >>> decoder = CommandDecoder()
    >>> decoder.feed(bytes.fromhex("50000050 0527103c 800080"))
    >>> list(decoder.events())  # doctest: +NORMALIZE_WHITESPACE
    [Write(register=<Rs232Register.POSITION_HIGH: 80>, value=0),
     Write(register=<Rs232Register.POSITION_LOW: 5>, value=10000), MonitorRequest()]
    """

    sizes: ClassVar = {
        **dict.fromkeys(WRITABLE, FRAME_SIZE),
        MONITOR_REQUEST_ADDRESS: len(MONITOR_REQUEST),
    }

    def _decode(self, frame: bytes) -> Command | Discarded:
        if frame[0] == MONITOR_REQUEST_ADDRESS:
            if frame != MONITOR_REQUEST:  # 80 80 00 passes its sum: 80 00 80 may be next
                return Discarded(frame[:1], "a monitor request carries no data")
            return MonitorRequest()
        codes = CODES.get(frame[0])
        value = _word(frame)
        return Write(Rs232Register(frame[0]), value if codes is None else named(codes, value))


_MONITOR_BUILDERS: dict[int, Callable[[int], Reply]] = {
    MonitorItem.STATUS: lambda value: StatusReport(AlarmFlags(value)),
    MonitorItem.BUS_VOLTAGE: BusVoltage,
    MonitorItem.CURRENT: OutputCurrent,
    MonitorItem.SPEED: OutputSpeed,
    **{item: partial(PositionWord, item) for item in POSITION_ITEMS},
}


class ReplyDecoder(_FirstByteFramed[Reply]):
    """Decodes the driver's frames, as the host sees them.

    >>> decoder = ReplyDecoder()
    >>> decoder.feed(bytes.fromhex("0909 e1001cfd"))
    >>> list(decoder.events())
    [Ack(register=<Rs232Register.POSITION_RAMP: 9>), BusVoltage(voltage_v=28)]
    """

    sizes: ClassVar = {**dict.fromkeys(WRITABLE, ACK_SIZE), **dict.fromkeys(MONITOR, FRAME_SIZE)}

    def _check_byte(self, frame: bytes) -> int:
        # An ack has no checksum: its second byte repeats the first, and that is the check.
        return frame[0] if len(frame) == ACK_SIZE else sum8(frame[:-1])

    def _decode(self, frame: bytes) -> Reply:
        if len(frame) == ACK_SIZE:
            return Ack(Rs232Register(frame[0]))
        return _MONITOR_BUILDERS[frame[0]](_word(frame))
