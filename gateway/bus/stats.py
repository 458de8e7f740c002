"""Bus statistics: counters the bus thread updates, and the frozen snapshot others read.

Rules: only the bus thread writes counters; ``snapshot()`` may be called from any thread and
takes the lock only to copy the follow-interval samples. Percentiles are over the last
``SAMPLES`` follow intervals, so memory stays bounded on a run of any length.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, fields, replace
from typing import Any

SAMPLES = 10_000


@dataclass(frozen=True, slots=True)
class BusStats:
    """A bus's statistics at one moment (times in seconds, utilisation 0–1)."""

    frames_out: int
    frames_in: int
    bytes_out: int
    bytes_in: int
    timeouts: int
    retries: int
    checksum_errors: int
    discarded_bytes: int
    late_replies: int
    early_replies: int
    reconnects: int
    skipped_polls: int
    busy_commands: int
    smallest_gap_s: float | None
    follow_error_p50_s: float | None
    follow_error_p99_s: float | None
    follow_error_min_s: float | None
    follow_intervals: int
    utilisation: float
    uptime_s: float


class BusCounters:
    """The live counters of one bus (written by its thread only)."""

    def __init__(self, started: float) -> None:
        self.started = started
        self.frames_out = self.frames_in = self.bytes_out = self.bytes_in = 0
        self.timeouts = self.retries = self.checksum_errors = self.discarded_bytes = 0
        self.late_replies = self.reconnects = self.skipped_polls = self.busy_commands = 0
        self.early_replies = 0
        self.busy_s = 0.0
        self.smallest_gap_s: float | None = None
        self._follow_errors: deque[float] = deque(maxlen=SAMPLES)
        self._follow_count = 0
        self._lock = threading.Lock()

    def gap(self, gap_s: float) -> None:
        if self.smallest_gap_s is None or gap_s < self.smallest_gap_s:
            self.smallest_gap_s = gap_s

    def follow_interval(self, interval_s: float, period_s: float) -> None:
        with self._lock:
            self._follow_errors.append(interval_s - period_s)
            self._follow_count += 1

    def snapshot(self, now: float) -> BusStats:
        with self._lock:
            errors = sorted(self._follow_errors)
            count = self._follow_count
        elapsed = max(now - self.started, 1e-9)
        return BusStats(
            frames_out=self.frames_out,
            frames_in=self.frames_in,
            bytes_out=self.bytes_out,
            bytes_in=self.bytes_in,
            timeouts=self.timeouts,
            retries=self.retries,
            checksum_errors=self.checksum_errors,
            discarded_bytes=self.discarded_bytes,
            late_replies=self.late_replies,
            early_replies=self.early_replies,
            reconnects=self.reconnects,
            skipped_polls=self.skipped_polls,
            busy_commands=self.busy_commands,
            smallest_gap_s=self.smallest_gap_s,
            follow_error_p50_s=percentile(errors, 0.50),
            follow_error_p99_s=percentile(errors, 0.99),
            follow_error_min_s=errors[0] if errors else None,
            follow_intervals=count,
            utilisation=min(1.0, self.busy_s / elapsed),
            uptime_s=elapsed,
        )


def percentile(ordered: list[float], q: float) -> float | None:
    """The nearest-rank ``q`` percentile of an ascending list (``None`` when empty).

    >>> percentile([1.0, 2.0, 3.0, 4.0], 0.5), percentile([1.0, 2.0, 3.0, 4.0], 0.99)
    (2.0, 4.0)
    """
    if not ordered:
        return None
    rank = max(1, math.ceil(q * len(ordered)))
    return ordered[rank - 1]


#: The fields of ``BusStats`` that count since the bus started (the rest are of the moment).
COUNTS = tuple(f.name for f in fields(BusStats) if f.type == "int")


def carried(before: BusStats, later: BusStats, *, reconnects: int = 0) -> BusStats:
    """``later``'s statistics with ``before``'s counts, its time up and its smallest gap
    taken in, and ``reconnects`` more: a bus whose counters started again (its worker did)
    counts on, as a counter must (Prometheus takes a fall for a reset), and its rates stay
    rates (``busgate watch`` divides the counts by the time up)."""
    added: dict[str, Any] = {name: getattr(before, name) + getattr(later, name) for name in COUNTS}
    added["reconnects"] += reconnects
    added["uptime_s"] = before.uptime_s + later.uptime_s
    gaps = [g for g in (before.smallest_gap_s, later.smallest_gap_s) if g is not None]
    added["smallest_gap_s"] = min(gaps) if gaps else None
    return replace(later, **added)
