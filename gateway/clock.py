"""Precise waiting on a general-purpose OS: sleep most of the way, spin the rest.

``time.sleep`` overshoots by 50–100 µs (and by milliseconds under load), so every timing
loop (the simulators' reply timing, the bus scheduler) waits through ``sleep_until``: it
sleeps until ``SPIN_S`` before the absolute deadline, then spins on ``perf_counter``.
Deadlines are absolute ``time.perf_counter()`` values so that lateness never accumulates.
"""

from __future__ import annotations

import time

SPIN_S = 0.0006

now = time.perf_counter


def sleep_until(deadline: float, *, spin_s: float = SPIN_S) -> float:
    """Return at ``deadline`` (a ``perf_counter`` time) or just after; return the time then."""
    remaining = deadline - now()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while (current := now()) < deadline:
        pass
    return current
