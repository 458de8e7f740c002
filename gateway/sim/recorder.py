"""The simulators' record of the wire: one JSON line per frame, in either direction.

Times are ``time.perf_counter()`` seconds, which on Linux is CLOCK_MONOTONIC and so comparable
across processes: ``start`` is when the frame's first byte went on the wire and ``end`` when its
last byte left it, so gaps and follow periods can be measured on the device side. Received
frames also carry ``arrived``, when the simulator read them off the pty: frames read in one go
were written in one burst, or waited while the simulator's thread did not run (a loaded host
starves it): either way their spacing on the wire cannot be told from the device side, and
the host's own write times say what the gateway kept.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from typing import IO


@dataclass(frozen=True, slots=True)
class WireRecord:
    direction: str  # "rx": host → device, "tx": device → host
    start: float
    end: float
    wire: str  # hex, or id#data for CAN
    frame: str  # the decoded event's class name
    device_id: int | None = None
    arrived: float | None = None

    def to_json(self) -> str:
        return json.dumps(
            {
                "dir": self.direction,
                "start": round(self.start, 7),
                "end": round(self.end, 7),
                "wire": self.wire,
                "frame": self.frame,
                "device_id": self.device_id,
                "arrived": None if self.arrived is None else round(self.arrived, 7),
            }
        )

    @classmethod
    def from_json(cls, line: str) -> WireRecord:
        item = json.loads(line)
        return cls(
            item["dir"],
            item["start"],
            item["end"],
            item["wire"],
            item["frame"],
            item["device_id"],
            item.get("arrived"),
        )


class Recorder:
    """Keeps the last ``keep`` records in memory (``records``: what tests read) and, when given
    a file, appends JSON lines. ``keep=0`` keeps none: a demo or a simulator that runs for days
    reads nothing back, and 100,000 records a simulator held some 35 MB each."""

    def __init__(self, stream: IO[str] | None = None, *, keep: int = 100_000) -> None:
        self._stream = stream
        self._keep = keep
        self._lock = threading.Lock()
        self.records: list[WireRecord] = []

    def record(self, record: WireRecord) -> None:
        with self._lock:
            if self._keep:
                self.records.append(record)
                if len(self.records) > self._keep:
                    del self.records[: len(self.records) - self._keep]
            if self._stream is not None:
                self._stream.write(record.to_json() + "\n")
                self._stream.flush()

    def received(self) -> list[WireRecord]:
        """The frames the devices received, in order."""
        with self._lock:
            return [r for r in self.records if r.direction == "rx"]
