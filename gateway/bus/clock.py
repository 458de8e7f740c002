"""Precise waiting on a general-purpose OS: sleep most of the way, spin the rest.

``time.sleep`` overshoots (by the thread's timer slack, 50 µs by default on Linux, and by
milliseconds under load), so every timing loop (the simulators' reply timing, the bus
scheduler) waits through ``sleep_until``: it sleeps until a lead before the absolute deadline,
then spins on ``perf_counter``. The lead is what the kernel's wake-ups have been late by on
this thread (``WakeUpLead``, learnt at every wait, at most ``SPIN_S``): a fixed 250 µs spin
before every frame was half the CPU of eight buses, and N spinning threads took turns on the
GIL, while the wake-ups here are late by some 50 µs. Deadlines are absolute
``time.perf_counter()`` values so that lateness never accumulates.

Two process settings matter as much: a timing thread asks for a 1 ns timer slack
(``tighten_timer_slack``), and the interpreter's GIL switch interval is cut from 5 ms to
0.2 ms (``tune_interpreter``), so a bus thread waiting for the GIL behind another Python
thread has it handed over after 0.2 ms, not 5.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
import threading
import time

log = logging.getLogger(__name__)

#: The most a wait spins: the lead a thread starts with, and the most it learns.
SPIN_S = 0.00025
#: The weight of each new wake-up in the learnt lead.
LEARNING_RATE = 0.1
#: The shortest sleep worth its syscall: shorter, it is spun. A wake-up is later than this
#: here, and it is the most a lead just learnt can leave beyond itself after a wait that
#: ended at the lead before it (``woke_for``, then ``sleep_until``).
MIN_SLEEP_S = LEARNING_RATE * SPIN_S
SWITCH_INTERVAL_S = 0.0002
_PR_SET_NAME = 15
_PR_SET_TIMERSLACK = 29

#: The bus clock: ``CLOCK_MONOTONIC`` on Linux (``time.get_clock_info("perf_counter")``), kept
#: by the kernel for the whole host, not per process (a worker, a child of the daemon, is in
#: its time namespace): a time taken in the gateway's process means the same in a worker's (a
#: trajectory's start, when a follow target was taken).
now = time.perf_counter


class WakeUpLead(threading.local):
    """How early one thread asks to be woken: the mean lateness of its wake-ups (a running
    average), between none and ``SPIN_S``. A wake-up later than the lead costs that lateness
    once; an earlier one, a spin of the difference."""

    def __init__(self) -> None:
        self.lead_s = SPIN_S

    def learn(self, late_s: float) -> None:
        """A sleep that was to end ``lead_s`` before its deadline ended ``late_s`` after that."""
        late_s = min(max(late_s, 0.0), SPIN_S)
        self.lead_s += LEARNING_RATE * (late_s - self.lead_s)


_lead = WakeUpLead()


def wake_lead() -> float:
    """How long before a precise deadline the calling thread asks to be woken (its learnt
    lead): a wait of its own (one new work may cut short) ends there, and ``sleep_until``
    spins the rest."""
    return _lead.lead_s


def woke_for(asked: float) -> None:
    """The calling thread, whose wait was to end at ``asked`` (its lead before a deadline),
    is awake: its lead learns how late."""
    _lead.learn(now() - asked)


def sleep_until(deadline: float, *, spin_s: float | None = None) -> float:
    """Return at ``deadline`` (a ``perf_counter`` time) or just after; return the time then.
    The sleep ends the thread's learnt lead before it (``spin_s``: that lead instead, not
    learnt from; 0 never spins), the rest is spun; a sleep shorter than ``MIN_SLEEP_S`` is
    spun too (but for ``spin_s=0``)."""
    lead = _lead.lead_s if spin_s is None else spin_s
    shortest_sleep = 0.0 if spin_s == 0 else MIN_SLEEP_S
    remaining = deadline - now()
    if remaining - lead > shortest_sleep:
        time.sleep(remaining - lead)
        if spin_s is None:
            woke_for(deadline - lead)
    while (current := now()) < deadline:
        pass
    return current


def tighten_timer_slack() -> bool:
    """Ask Linux for a 1 ns timer slack for the calling thread; ``False`` where unsupported."""
    return _prctl(_PR_SET_TIMERSLACK, 1)


def ask_realtime(priority: int, who: str) -> bool:
    """Run the calling thread under SCHED_FIFO at ``priority``; refused (no privilege), a
    warning naming ``who``, and it runs at normal priority."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        log.warning("%s: SCHED_FIFO %d refused (%s); normal priority", who, priority, exc)
        return False
    return True


def name_thread(name: str) -> bool:
    """Give the calling thread ``name`` (its first 15 bytes) where ``top -H``, ``ps -L`` and
    /proc show it, so that a bus thread's CPU is seen as its own; ``False`` where unsupported."""
    return _prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]))


def _prctl(option: int, argument: object) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    return libc.prctl(option, argument, 0, 0, 0) == 0


def tune_interpreter() -> None:
    """Make GIL hand-overs quick enough for millisecond timing (process-wide)."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
