"""The owner of one serial port (UART or RS485 through a USB adapter): a ``BusOwner``.

Rules of this file:

1. Stale input is flushed right before every request, and any reply that *could not* be the
   answer is ignored: one read before our frame had left the wire plus the device's shortest
   reply time is counted ``early`` (a wrong baud rate, or an emulator without wire timing), one
   left from an earlier exchange ``late``. A reply that arrives after its timeout is never
   taken for the next request's reply.
2. The gap counts from the last byte seen on the line: when the flush finds anything (a late
   reply, noise), the write waits until ``gap_s`` has passed since then, and looks again. The
   exchange says when that byte was read (``last_byte_before``), so the gap statistic counts
   from it too. After a frame that gets no reply, the line is free once the frame has left
   the port's driver (``tty_write.left_driver``: a USB adapter's sends a moment after the
   write) and then the wire.
3. ``SerialException`` and ``OSError`` mean the link is down: the port is closed at once and
   ``BusIOError`` raised.
4. Waiting for a reply uses ``select`` on the port's descriptor with the absolute deadline,
   so a timeout costs no polling and a reply is read the moment it lands.
5. Nothing comes unasked on a question-and-answer line: the owner has no idle work.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
from types import ModuleType
from typing import ClassVar

import serial

from busgate.codecs.framing import ChecksumMismatch, Discarded, ExpectedReply
from busgate.errors import BusIOError, BusUnavailableError, DeviceTimeoutError
from busgate.gateway.bus.clock import now, sleep_until
from busgate.gateway.bus.owner import RX, TX, BusOwner
from busgate.gateway.bus.port_access import describe_open_error
from busgate.gateway.bus.request import Exchange, LinkTiming, Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.bus.tty_write import left_driver, write_all

#: How long a write may wait for the port to take its bytes (a wedged adapter) before the
#: link counts as lost.
WRITE_TIMEOUT_S = 0.5
#: Longest a write waits for a line that keeps talking (noise) to fall quiet for the gap.
QUIET_WAIT_MAX_S = 0.05


class SerialBusOwner(BusOwner):
    """Runs exchanges on one serial port, one at a time."""

    idle_batch_s: ClassVar[float] = math.inf  # rule 5: idle time is only waiting

    def __init__(
        self, port: str, codec: ModuleType, timing: LinkTiming, counters: BusCounters
    ) -> None:
        self.port = port
        self.codec = codec
        self.timing = timing
        self.counters = counters
        self._serial: serial.Serial | None = None
        self._decoder = codec.ReplyDecoder()
        self._early = 0  # replies of the exchange in progress that came too early
        self._last_byte = -math.inf  # when a byte was last read off the line (rule 2)

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port exclusively; ``BusUnavailableError`` when it cannot be had."""
        try:
            self._serial = serial.Serial(
                self.port,
                self.timing.rate,
                timeout=0,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise BusUnavailableError(describe_open_error(self.port, exc)) from exc
        self._decoder = self.codec.ReplyDecoder()

    def close(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):  # may be gone already
                port.close()

    def exchange(self, request: Request, *, at: float | None = None) -> Exchange:
        if self._serial is None:
            raise BusIOError(f"{self.port} is not open")
        try:
            return self._exchange(self._serial, request, at)
        except DeviceTimeoutError:
            raise  # a TimeoutError is an OSError too, but the link is fine
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise BusIOError(f"{self.port}: {exc}") from exc

    def _exchange(self, port: serial.Serial, request: Request, at: float | None) -> Exchange:
        if at is not None:
            sleep_until(at)
        self._wait_for_quiet(port)
        last_byte = self._last_byte
        # Two clocks on the write: the frame cannot have left before ``issued`` (so no true
        # reply can come before issued + wire + shortest reply time), and the line is taken
        # until at least ``start`` + wire time, ``start`` being when the kernel had the bytes.
        issued = now()
        assert isinstance(request.wire, bytes)  # a UART codec's frames
        self._write(port, request.wire)
        start = now()
        # No reply to say when the line was free: it is once the frame has left the port's
        # driver (a USB adapter's, a moment after the write; looked at first, before anything
        # else delays the look), and then the wire.
        left = left_driver(port.fileno(), start) if request.expected is None else start
        if self.tap is not None:
            self.tap((start, TX, request.wire, None))
        wire_time = self.timing.wire_time(request.wire)
        self.counters.frames_out += 1
        self.counters.bytes_out += len(request.wire)
        reply: tuple[object, ...] = ()
        if request.expected is None:
            end = left + wire_time
        else:
            earliest, latest = self.timing.reply_window(request)
            end, reply = self._wait_reply(
                port, request.expected, issued + wire_time + earliest, start + wire_time + latest
            )
        return Exchange(
            request, start, end, reply, write_s=start - issued, last_byte_before=last_byte
        )

    def take_unsolicited(self) -> None:
        """Nothing to take (rule 5): whatever is on the line between exchanges is a late reply
        or noise, flushed and counted right before the next write."""

    def _write(self, port: serial.Serial, wire: bytes) -> None:
        """One ``write`` syscall for the whole frame in the usual case (pyserial's ``write``
        adds a ``select`` after it, and spins while the port takes no bytes)."""
        if not write_all(port.fileno(), wire, WRITE_TIMEOUT_S):
            raise serial.SerialTimeoutException(
                f"write timeout: the port took no more bytes for {WRITE_TIMEOUT_S:g} s"
            )

    def _wait_reply(
        self, port: serial.Serial, expected: ExpectedReply, earliest: float, deadline: float
    ) -> tuple[float, tuple[object, ...]]:
        """When the answer's last byte was read, and its events."""
        answer: list[object] = []
        self._early = 0
        fd = port.fileno()
        while True:
            # Past the deadline, one last look without waiting: a reply that came in time
            # while this thread was held up (scheduling, the GIL) is still taken.
            remaining = deadline - now()
            if not select.select([fd], [], [], max(remaining, 0.0))[0]:
                break
            data = os.read(fd, 4096)
            if not data:
                raise serial.SerialException("the port reports data but returns none (unplugged?)")
            arrived = self._last_byte = now()
            if self.tap is not None:
                self.tap((arrived, RX, data, None))
            self.counters.bytes_in += len(data)
            self._decoder.feed(data)
            for event in self._decoder.events():
                if self._take(event, expected, arrived >= earliest):
                    answer.append(event)
            if len(answer) >= expected.frames:
                return arrived, tuple(answer)
            if remaining <= 0:
                break
        self.counters.timeouts += 1
        who = "the device" if expected.source_id is None else f"id {expected.source_id}"
        message = f"no reply from {who} on {self.port}"  # RS232's one device has no id
        if self._early:
            message += (
                f"; {self._early} came before the request could have left the wire at "
                f"{self.timing.rate} baud: is the baud rate right, or is this an "
                "emulator without wire timing?"
            )
        raise DeviceTimeoutError(message, device_id=expected.source_id)

    def _take(self, event: object, expected: ExpectedReply, in_time: bool) -> bool:
        """Count ``event``; true when it is (part of) the awaited answer."""
        if isinstance(event, Discarded):
            self.counters.discarded_bytes += len(event.data)
            return False
        if isinstance(event, ChecksumMismatch):
            self.counters.checksum_errors += 1
            return False
        self.counters.frames_in += 1
        if not expected.matches(event):
            self.counters.late_replies += 1
            return False
        if not in_time:
            self.counters.early_replies += 1
            self._early += 1
            return False
        return True

    def _wait_for_quiet(self, port: serial.Serial) -> None:
        """Flush stale input; while there was some, wait out the gap after it and look again."""
        give_up = now() + QUIET_WAIT_MAX_S
        while self._flush_stale(port) and now() < give_up:
            sleep_until(now() + self.timing.gap_s)

    def _flush_stale(self, port: serial.Serial) -> bool:
        """Drop whatever arrived since the last exchange (late replies, noise); true when
        there was any (it was on the line a moment ago)."""
        waiting = port.in_waiting
        if waiting:
            data = port.read(waiting)
            self._last_byte = now()
            if self.tap is not None:
                self.tap((self._last_byte, RX, data, None))
            self._decoder.feed(data)
            for event in self._decoder.events():
                if isinstance(event, Discarded):
                    self.counters.discarded_bytes += len(event.data)
                else:
                    self.counters.late_replies += 1
        self.counters.discarded_bytes += self._decoder.pending
        self._decoder = self.codec.ReplyDecoder()
        return bool(waiting)
