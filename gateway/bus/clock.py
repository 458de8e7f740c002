"""Precise waiting on a general-purpose OS: sleep most of the way, spin the rest.

``time.sleep`` overshoots (by the thread's timer slack, 50 µs by default on Linux, and by
milliseconds under load), so every timing loop (the simulators' reply timing, the bus
scheduler) waits through ``sleep_until``: it sleeps until ``SPIN_S`` before the absolute
deadline, then spins on ``perf_counter``. Deadlines are absolute ``time.perf_counter()``
values so that lateness never accumulates.

Two process settings matter as much: a timing thread asks for a 1 ns timer slack
(``tighten_timer_slack``), and the interpreter's GIL switch interval is cut from 5 ms to
0.5 ms (``tune_interpreter``), so a bus thread waiting for the GIL behind another Python
thread waits half a millisecond at most, not five.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import time

SPIN_S = 0.00025
SWITCH_INTERVAL_S = 0.0002
_PR_SET_TIMERSLACK = 29

now = time.perf_counter


def sleep_until(deadline: float, *, spin_s: float = SPIN_S) -> float:
    """Return at ``deadline`` (a ``perf_counter`` time) or just after; return the time then."""
    remaining = deadline - now()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while (current := now()) < deadline:
        pass
    return current


def tighten_timer_slack() -> bool:
    """Ask Linux for a 1 ns timer slack for the calling thread; ``False`` where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    return libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0


def tune_interpreter() -> None:
    """Make GIL hand-overs quick enough for millisecond timing (process-wide)."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
