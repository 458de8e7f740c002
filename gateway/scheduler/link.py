"""A bus that is down: how long to wait before trying it again, and what is said about it.

Its own module because it is timing logic with rules of its own, kept apart from the bus
thread that carries it out so that it is tested on a fake clock (the caller passes the time).

1. The waits between attempts to open the bus double from ``BACKOFF_FIRST_S`` to
   ``BACKOFF_MAX_S`` and no further; once the bus is up, the next loss starts over.
2. The first failed attempt is logged; while the bus stays down, at most one summary every
   ``DOWN_REPORT_S`` (for how long, after how many attempts).
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

BACKOFF_FIRST_S, BACKOFF_MAX_S = 0.1, 2.0
#: How often a bus that stays down is reported again after its first warning.
DOWN_REPORT_S = 60.0


class Reconnect:
    """The attempts to open one bus."""

    def __init__(self, bus: str) -> None:
        self.bus = bus
        self._backoff = BACKOFF_FIRST_S
        self._up_before = False
        self._down_since: float | None = None
        self._reported = 0.0
        self._attempts = 0

    def failed(self, exc: Exception, moment: float) -> float:
        """An attempt failed at ``moment`` with ``exc``: reported (rule 2); how long to wait
        before the next one (rule 1)."""
        self._attempts += 1
        if self._down_since is None:
            self._down_since = self._reported = moment
            self._attempts = 0
            log.warning(
                "bus %s down: %s; retrying every %.1f-%.0f s",
                self.bus,
                exc,
                BACKOFF_FIRST_S,
                BACKOFF_MAX_S,
            )
        elif moment - self._reported >= DOWN_REPORT_S:
            self._reported = moment
            log.warning(
                "bus %s still down after %.0f s (%d attempts): %s",
                self.bus,
                moment - self._down_since,
                self._attempts,
                exc,
            )
        wait, self._backoff = self._backoff, min(self._backoff * 2, BACKOFF_MAX_S)
        return wait

    def opened(self) -> bool:
        """The bus is up; whether it had been up before (then this is a reconnect)."""
        again, self._up_before = self._up_before, True
        self._down_since = None
        self._backoff = BACKOFF_FIRST_S
        return again
