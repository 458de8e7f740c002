"""When a device of one bus may be sent its next follow target, whatever sends it.

The Inspire LA's manual takes follow-mode targets only at a fixed period (3.5.3, 3.7.2:
"以固定的时间间隔（10ms~50ms）"), and each ticker keeps its own ticks a period apart
(``tickers`` rule 1, ``trajectory_ticks`` rule 1). But a device passes from one sender to
another: a command's ``follow`` then a stream, a stream then a trajectory or a command's
``group_follow``, one trajectory then the next on another ticker. Each sender alone keeps
the period; this keeps it across them.

Rules of this file:

1. Bus thread only. A sender is a ticker (a follow stream's or a trajectory's) or a
   command's job carrying follow-mode targets; ``Execution`` tells each one's frames as they
   go on the wire, the moment counted as the sender counts its own (a tick's start, a job's).
2. A device's next follow target from any other sender is due a follow period after its
   last one at the soonest (``due``); a sender's own next is its own rule's.
3. While a command carrying a device a follow-mode target waits to go out, no other sender
   sends that device one (when it will go is not known); once it went, or was taken out
   (its future settled), the others go on by rule 2.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from busgate.gateway.drivers.base import Driver
    from busgate.gateway.scheduler.planner import Job


class FollowSpacing:
    """Each device's last follow target on the wire, and what sent it (the rules above)."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[object, float]] = {}
        self._commands: dict[str, Job] = {}

    def commanded(self, devices: Iterable[str], job: Job) -> None:
        """``job``, a command's, carries each of ``devices`` a follow-mode target (rule 3)."""
        self._commands.update(dict.fromkeys(devices, job))

    def ticked(self, drivers: Iterable[Driver], ticker: object, at: float) -> None:
        """``ticker``'s frame, carrying ``drivers`` their targets, went at ``at``."""
        for driver in drivers:
            self._last[driver.name] = (ticker, at)

    def job_sent(self, job: Job, at: float) -> None:
        """A frame of ``job`` went at ``at``: the devices it carries targets have them then
        (its last frame's moment, when it has several)."""
        for device, command in self._commands.items():
            if command is job:
                self._last[device] = (job, at)

    def last(self, device: str) -> float | None:
        """When ``device``'s last follow target went, from any sender; ``-inf`` when none
        did, ``None`` while a command carrying it one waits (rule 3)."""
        if _waits(self._commands.get(device)):
            return None
        last = self._last.get(device)
        return -math.inf if last is None else last[1]

    def due(self, device: str, period_s: float, sender: object) -> float:
        """The soonest ``sender`` may send ``device`` a follow target (rules 2 and 3):
        ``-inf`` when nothing else sent it one, ``inf`` while a command's waits."""
        command = self._commands.get(device)
        if command is not sender and _waits(command):
            return math.inf
        last = self._last.get(device)
        if last is None or last[0] is sender:
            return -math.inf
        return last[1] + period_s


def _waits(job: Job | None) -> bool:
    """Whether ``job`` still has frames to send, its client still waiting for them."""
    if job is None or not job.requests:
        return False
    return job.future is None or not job.future.done()
