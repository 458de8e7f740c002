"""Figures from a simulator's wire record, seen from the device side: gaps and follow periods.

The host measures its own timing (``BusStats``); this measures what reached the devices, from
the records a simulator writes (``--record``). Two limits of measuring on this side:

- Frames the simulator read off the pty in one go were written in one burst, so the gap
  between them cannot be resolved here; they are counted apart (``unresolved``).
- A received frame's time is when the simulator read it, which is late by the simulator's own
  wake-up latency (tens to hundreds of µs on a loaded machine). A gap after the device's reply
  is measured from the simulator's own send time, so it is exact or overstated; a gap after a
  frame that has no reply is the difference of two such read times, so read jitter can make it
  look shorter than it was. The two are reported apart.
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from pathlib import Path

from busgate.gateway.bus.stats import percentile
from busgate.gateway.sim.recorder import WireRecord

#: Records keep times to 0.1 µs (``WireRecord.to_json``): an interval counts as shorter than
#: the period only by more than that.
RESOLUTION_S = 1e-7


@dataclass(frozen=True, slots=True)
class WireFigures:
    frames_received: int
    smallest_gap_after_reply_s: float | None
    gaps_after_reply_below_minimum: int
    smallest_gap_after_silent_frame_s: float | None
    gaps_after_silent_frame_below_minimum: int
    unresolved: int
    follow_frames: int
    smallest_follow_interval_s: float | None
    follow_intervals_under_period: int
    follow_error_p50_s: float | None
    follow_error_p99_s: float | None
    mean_turnaround_s: float | None


def load_records(path: str | Path) -> list[WireRecord]:
    """The records of a file, but a last line still being written (no newline yet)."""
    with open(path) as stream:
        return [
            WireRecord.from_json(line) for line in stream if line.endswith("\n") and line.strip()
        ]


def analyse(
    records: Iterable[WireRecord],
    *,
    min_gap_s: float,
    follow_frames: Collection[str] = (),
    follow_period_s: float | None = None,
) -> WireFigures:
    """Device-side gaps (each received frame's start after the previous frame's end, either
    direction) and intervals between consecutive follow frames to the same device (a
    broadcast frame, which carries every device's target, counts as one stream)."""
    ordered = sorted(records, key=lambda r: r.start)
    after_reply: list[float] = []
    after_silent: list[float] = []
    unresolved = 0
    turnarounds: list[float] = []
    previous: WireRecord | None = None
    line_idle = None
    for record in ordered:
        if record.direction == "rx" and previous is not None and line_idle is not None:
            if record.arrived is not None and record.arrived == previous.arrived:
                unresolved += 1
            else:
                gaps = after_reply if previous.direction == "tx" else after_silent
                gaps.append(record.start - line_idle)
        if record.direction == "tx" and previous is not None and previous.direction == "rx":
            turnarounds.append(record.start - previous.end)
        line_idle = record.end if line_idle is None else max(line_idle, record.end)
        previous = record
    ticks = [r for r in ordered if r.direction == "rx" and r.frame in follow_frames]
    streams: dict[int | None, list[WireRecord]] = {}  # one per device (a broadcast is one)
    for tick in ticks:
        streams.setdefault(tick.device_id, []).append(tick)
    intervals = [
        b.start - a.start
        for stream in streams.values()
        for a, b in itertools.pairwise(stream)
        if b.arrived is None or b.arrived != a.arrived
    ]
    errors = sorted(i - follow_period_s for i in intervals) if follow_period_s else []
    shortest_gap = min_gap_s - RESOLUTION_S
    return WireFigures(
        frames_received=sum(1 for r in ordered if r.direction == "rx"),
        smallest_gap_after_reply_s=min(after_reply, default=None),
        gaps_after_reply_below_minimum=sum(1 for g in after_reply if g < shortest_gap),
        smallest_gap_after_silent_frame_s=min(after_silent, default=None),
        gaps_after_silent_frame_below_minimum=sum(1 for g in after_silent if g < shortest_gap),
        unresolved=unresolved,
        follow_frames=len(ticks),
        smallest_follow_interval_s=min(intervals, default=None),
        follow_intervals_under_period=sum(1 for e in errors if e < -RESOLUTION_S),
        follow_error_p50_s=percentile(errors, 0.5),
        follow_error_p99_s=percentile(errors, 0.99),
        mean_turnaround_s=sum(turnarounds) / len(turnarounds) if turnarounds else None,
    )
