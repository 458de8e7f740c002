"""What travels between the scheduler and a bus owner: a request, its timing, its result.

``LinkTiming`` is the one place where a request's worst-case duration and reply deadline are
computed, from wire time at the bus's rate and the device family's stated reply time, so the
scheduler's budget and the owner's timeout can never disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import ModuleType

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import ExpectedReply
from busgate.codecs.timing import ProtocolTiming, can_time, uart_time


@dataclass(frozen=True, slots=True)
class Request:
    """One frame to send and the reply it brings (``expected`` is ``None`` when none comes).

    ``idempotent`` requests (reads, status queries, absolute targets) may be retried after a
    timeout or a corrupted reply; the others are sent once.
    """

    frame: object
    wire: bytes | CanFrame
    expected: ExpectedReply | None
    idempotent: bool = False

    @classmethod
    def of(cls, codec: ModuleType, frame: object, *, idempotent: bool = False) -> Request:
        """Encode ``frame`` with ``codec`` and ask it what reply to expect."""
        return cls(frame, codec.encode(frame), codec.expected_reply(frame), idempotent)


@dataclass(frozen=True, slots=True)
class Exchange:
    """A finished exchange: when the kernel had our frame (``start``, just after the write
    call, which took ``write_s``), when the line went idle again (the reply's last byte read,
    or our last byte's wire time), and the reply's events."""

    request: Request
    start: float
    end: float
    reply: tuple[object, ...] = field(default_factory=tuple)
    write_s: float = 0.0
    #: When the owner last read a byte off the line before this write (a late reply it
    #: flushed, noise); ``-inf`` when it never did, or cannot tell (CAN).
    last_byte_before: float = -math.inf


@dataclass(frozen=True, slots=True)
class LinkTiming:
    """Timing of one bus: its rate, the devices' reply time and the margin on top.

    ``rate`` is baud for a UART, bit/s for CAN. ``margin_s`` covers what the manuals cannot
    know: USB adapter latency and the host's own scheduling.
    """

    protocol: str
    #: The protocol's own figures (its codec's ``TIMING``), and whether its frames are CAN's.
    protocol_timing: ProtocolTiming
    can: bool
    rate: int
    margin_s: float
    gap_s: float = 0.0

    def wire_time(self, wire: bytes | CanFrame) -> float:
        """Seconds ``wire`` occupies the line."""
        if isinstance(wire, CanFrame):
            return can_time(len(wire.data), self.rate)
        return uart_time(len(wire), self.rate)

    def reply_time(self, expected: ExpectedReply) -> float:
        """Seconds the expected reply occupies the line, at most."""
        if self.can:
            return expected.frames * can_time(expected.wire_bytes, self.rate)
        return uart_time(expected.wire_bytes, self.rate)

    def reply_window(self, request: Request) -> tuple[float, float]:
        """From the end of our frame: (earliest a true reply can start, latest it may end)."""
        if request.expected is None:
            return 0.0, 0.0
        timing = self.protocol_timing
        latest = timing.reply_max_s + self.reply_time(request.expected) + self.margin_s
        return timing.reply_min_s, latest

    def worst_case(self, request: Request) -> float:
        """Longest the exchange can hold the line: our frame, then the reply or its timeout."""
        return self.wire_time(request.wire) + self.reply_window(request)[1]
