"""Serves simulated CAN devices on a python-can bus with the timing of a real CAN bus.

Rules of this file:

1. A command frame counts as received one frame time (worst-case bit stuffing, at
   ``bitrate``) after it arrived or the bus was last free; a reply goes out after the device's
   turnaround plus its own frame time. python-can's ``virtual`` bus delivers instantly, so the
   delay is added here.
2. Devices also talk unasked (heartbeats, alarm reports): the loop wakes for them.
3. CAN frames carry no checksum of ours (the controller's CRC guards them), so the faults that
   apply are drops, late replies and silent ids.
"""

from __future__ import annotations

import random
import threading
from collections.abc import Sequence
from types import ModuleType

import can

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import Discarded
from busgate.codecs.timing import can_time
from busgate.gateway.bus.clock import now, sleep_until
from busgate.gateway.sim.device import SimDevice
from busgate.gateway.sim.faults import FaultConfig, FaultInjector
from busgate.gateway.sim.recorder import Recorder, WireRecord

POLL_S = 0.005


class CanSimulator:
    """Devices of one protocol on one CAN bus (any python-can bus; ``virtual`` in process)."""

    def __init__(
        self,
        codec: ModuleType,
        devices: Sequence[SimDevice],
        *,
        bus: can.BusABC,
        bitrate: int = 500_000,
        faults: FaultInjector | None = None,
        recorder: Recorder | None = None,
        seed: int = 0,
    ) -> None:
        self.codec = codec
        self.devices = list(devices)
        self.bus = bus
        self.bitrate = bitrate
        self.faults = faults or FaultInjector(seed=seed)
        self.recorder = recorder or Recorder()
        self._random = random.Random(seed)
        self._decoder = codec.CommandDecoder()
        self._bus_free = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="sim-can", daemon=True)

    def start(self) -> CanSimulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.shutdown()

    def __enter__(self) -> CanSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self) -> None:
        while not self._stop.is_set():
            message = self.bus.recv(timeout=POLL_S)
            if message is not None:
                self._receive(message, now())
            for device in self.devices:
                for frame in device.spontaneous(now()):
                    self._send(frame, now())

    def _receive(self, message: can.Message, arrived: float) -> None:
        frame_time = can_time(len(message.data), self.bitrate)
        start = max(arrived, self._bus_free)
        end = self._bus_free = start + frame_time
        if message.is_extended_id or message.is_remote_frame or message.is_error_frame:
            self._record("rx", start, end, _text(message), "Discarded", None)
            return
        self._decoder.feed(CanFrame(message.arbitration_id, bytes(message.data)))
        for event in self._decoder.events():
            faults = self.faults.config  # as configured when the frame came in, before its record
            self._record(
                "rx",
                start,
                end,
                _text(message),
                type(event).__name__,
                getattr(event, "device_id", None),
            )
            if not isinstance(event, Discarded):
                self._dispatch(event, end, faults)

    def _dispatch(self, command: object, received: float, faults: FaultConfig) -> None:
        for device in self.devices:
            if not device.accepts(command) or device.device_id in faults.silent_ids:
                continue
            for reply in device.handle(command, received):
                low, high = device.turnaround_s
                self._send(reply, received + self._random.uniform(low, high), faults)

    def _send(self, frame: object, start: float, faults: FaultConfig | None = None) -> None:
        wire: CanFrame = self.codec.encode(frame)
        shaped = self.faults.shape(wire.data, checksummed=False, config=faults)
        if shaped.wire is None:
            return
        start = max(start + shaped.delay_s, self._bus_free)
        end = self._bus_free = start + can_time(len(wire.data), self.bitrate)
        sleep_until(end, spin_s=0.0)  # CAN has no gap rule to honour to the µs: no spinning
        self.bus.send(
            can.Message(arbitration_id=wire.arbitration_id, data=wire.data, is_extended_id=False)
        )
        self._record(
            "tx", start, end, str(wire), type(frame).__name__, getattr(frame, "device_id", None)
        )

    def _record(self, direction, start, end, wire, name, device_id) -> None:
        self.recorder.record(WireRecord(direction, start, end, wire, name, device_id))


def _text(message: can.Message) -> str:
    return f"{message.arbitration_id:03x}#{bytes(message.data).hex()}"
