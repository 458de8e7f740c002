"""Serves simulated devices on a pty with the timing of a real UART.

Rules of this file:

1. Wire time both ways: a host's frame is taken as complete only once its bytes would have
   crossed the line at ``baudrate`` (10 bits per byte), counted from when they arrived or the
   line was last free; a reply starts after the device's turnaround and each chunk of it is
   written when its last byte would have arrived, so no exchange is faster than on hardware.
2. The devices see commands in wire order; replies go out in order, one device at a time.
3. Faults are applied on the way out (``FaultInjector``), as they were configured when the
   command came in (before it is recorded): a test that sees the command on record and then
   changes the faults cannot race the replies; a silent id's device does nothing.
4. One thread owns the pty; other threads only call ``unplug``/``replug``/``faults``/``stop``.
5. With ``busy_poll_s``, the thread polls the pty without sleeping for that long after each
   frame, so a frame's arrival is timed to a few µs instead of a wake-up latency: right for a
   simulator in its own process (``busgate sim``), wrong beside the gateway in one process,
   where the spinning would contend for the GIL.
"""

from __future__ import annotations

import random
import select
import threading
from collections.abc import Sequence
from types import ModuleType

from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.codecs.timing import uart_time
from busgate.gateway.bus.clock import now, sleep_until
from busgate.gateway.sim.device import SimDevice
from busgate.gateway.sim.faults import FaultConfig, FaultInjector
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.recorder import Recorder, WireRecord

#: Replies are written in chunks of at most this much wire time.
CHUNK_S = 0.001
POLL_S = 0.05


class SerialSimulator:
    """Devices of one protocol on one simulated serial line."""

    def __init__(
        self,
        codec: ModuleType,
        devices: Sequence[SimDevice],
        *,
        baudrate: int,
        link: PtyLink | None = None,
        faults: FaultInjector | None = None,
        recorder: Recorder | None = None,
        seed: int = 0,
        busy_poll_s: float = 0.0,
    ) -> None:
        self.codec = codec
        self.busy_poll_s = busy_poll_s
        self._last_rx = -1e9
        self.devices = list(devices)
        self.baudrate = baudrate
        self.link = link or PtyLink()
        self.faults = faults or FaultInjector(seed=seed)
        self.recorder = recorder or Recorder()
        self._random = random.Random(seed)
        self._decoder = codec.CommandDecoder()
        #: The bytes fed to the decoder that no event has accounted for yet.
        self._unparsed = bytearray()
        self._rx_free = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="sim-serial", daemon=True)

    @property
    def port(self) -> str:
        """What a host opens: the symlink when there is one, else the pty."""
        return self.link.link or self.link.path

    @property
    def partial_frame(self) -> bytes:
        """Bytes received that are not (yet) a whole frame: a frame the host left half-written."""
        return bytes(self._unparsed)

    def start(self) -> SerialSimulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.link.close()

    def __enter__(self) -> SerialSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def unplug(self) -> None:
        """Pull the adapter: the pty and its symlink go away until ``replug``."""
        self.link.want(False)

    def replug(self) -> None:
        """Plug the adapter back in: a new pty, the symlink pointed at it."""
        self.link.want(True)

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self.link.sync():
                self._decoder, self._unparsed = self.codec.CommandDecoder(), bytearray()
                self._stop.wait(POLL_S)
                continue
            busy = now() - self._last_rx < self.busy_poll_s
            readable, _, _ = select.select([self.link], [], [], 0 if busy else POLL_S)
            if readable:
                data = self.link.read()
                if data:
                    self._last_rx = now()
                    self._receive(data, self._last_rx)

    def _receive(self, data: bytes, arrived: float) -> None:
        self._decoder.feed(data)
        self._unparsed += data
        line_start = max(arrived, self._rx_free)
        for event in self._decoder.events():
            faults = self.faults.config  # rule 3: taken before the command is on record
            wire = self._consumed()
            end = line_start + uart_time(len(wire), self.baudrate)
            self.recorder.record(
                WireRecord(
                    "rx",
                    line_start,
                    end,
                    wire.hex(),
                    type(event).__name__,
                    getattr(event, "device_id", None),
                    arrived,
                )
            )
            if not isinstance(event, Discarded | ChecksumMismatch):
                end = max(end, self._dispatch(event, end, faults))
            self._rx_free = line_start = end

    def _consumed(self) -> bytes:
        """The wire bytes of the event just taken from the decoder. Counted from what the
        decoder still holds rather than re-encoded, since a frame can decode yet be out of
        the encoder's ranges (a target of 2500), and a checksum mismatch consumes one byte."""
        used = len(self._unparsed) - self._decoder.pending
        wire = bytes(self._unparsed[:used])
        del self._unparsed[:used]
        return wire

    def _dispatch(self, command: object, received: float, faults: FaultConfig) -> float:
        """Hand ``command`` to the devices it addresses and send their replies; return when
        the last reply left the wire."""
        line_free = received
        for device in self.devices:
            if not device.accepts(command) or device.device_id in faults.silent_ids:
                continue
            low, high = device.turnaround_s
            start = max(line_free, received) + self._random.uniform(low, high)
            for reply in device.handle(command, received):
                # A reply of several frames (the ZLAC706 monitor) goes out back to back.
                line_free = start = self._send(self.codec.encode(reply), reply, start, faults)
        return line_free

    def _send(self, wire: bytes, reply: object, start: float, faults: FaultConfig) -> float:
        shaped = self.faults.shape(wire, config=faults)
        if shaped.wire is None:
            return start
        start += shaped.delay_s
        duration = uart_time(len(shaped.wire), self.baudrate)
        chunk = max(1, int(CHUNK_S * self.baudrate / 10))
        for offset in range(0, len(shaped.wire), chunk):
            piece = shaped.wire[offset : offset + chunk]
            sleep_until(start + uart_time(offset + len(piece), self.baudrate))
            self.link.write(piece)
        self.recorder.record(
            WireRecord(
                "tx",
                start,
                start + duration,
                shaped.wire.hex(),
                type(reply).__name__,
                getattr(reply, "device_id", None),
            )
        )
        return start + duration
