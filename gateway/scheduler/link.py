"""A bus that is down: how long to wait before trying it again, and what is said about it.

Its own module because it is timing logic with rules of its own, kept apart from the bus
thread that carries it out so that it is tested on a fake clock (the caller passes the time).

1. The waits between attempts to open the bus double from ``BACKOFF_FIRST_S`` to
   ``BACKOFF_MAX_S`` and no further; once the bus was up ``STABLE_S``, the next loss starts
   over.
2. The first failed attempt is logged; while the bus stays down, at most one summary every
   ``DOWN_REPORT_S`` (for how long, after how many attempts).
3. A bus lost within ``STABLE_S`` of opening (it opens, then fails at once: a USB adapter
   that takes no more bytes) was not up: it is opened again after the backoff, which goes on
   doubling, not at once; its first such loss is logged, then at most one summary every
   ``DOWN_REPORT_S``, and once it has stayed up ``STABLE_S``, one line says so.
"""

from __future__ import annotations

import logging
import math

log = logging.getLogger(__name__)

BACKOFF_FIRST_S, BACKOFF_MAX_S = 0.1, 2.0
#: How long a bus must stay up for its loss to start the backoff over (rule 3).
STABLE_S = 5.0
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
        #: When the bus last opened; since then, how often it was lost within ``STABLE_S``
        #: of opening (rule 3), the last of those losses reported when.
        self._up_at: float | None = None
        self.quick_losses = 0
        self._losses_reported = 0.0
        #: Not to be opened again before this moment (rule 3).
        self.retry_at = -math.inf

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
        return self._next_wait()

    def _next_wait(self) -> float:
        """The wait before the next attempt, the one after it doubled (rule 1)."""
        wait, self._backoff = self._backoff, min(self._backoff * 2, BACKOFF_MAX_S)
        return wait

    def opened(self, moment: float) -> bool:
        """The bus is up at ``moment``; whether it had been up before (a reconnect)."""
        again, self._up_before = self._up_before, True
        self._down_since = None
        self._up_at = moment
        if not self.quick_losses:
            self._backoff = BACKOFF_FIRST_S
        return again

    def lost(self, exc: Exception, moment: float) -> bool:
        """The bus was lost at ``moment`` with ``exc``: whether the caller logs it (rule 3;
        a loss that is one of many is summed up here instead)."""
        if self._up_at is None or moment - self._up_at >= STABLE_S:
            self.quick_losses = 0
            self.retry_at = -math.inf
            return True
        self.quick_losses += 1
        self.retry_at = moment + self._next_wait()
        if self.quick_losses == 1:
            self._losses_reported = moment
            return True
        if moment - self._losses_reported >= DOWN_REPORT_S:
            self._losses_reported = moment
            log.warning(
                "bus %s lost again within %.0f s of opening, %d times: %s; retrying every "
                "%.1f-%.0f s",
                self.bus,
                STABLE_S,
                self.quick_losses,
                exc,
                BACKOFF_FIRST_S,
                BACKOFF_MAX_S,
            )
        return False

    def still_up(self, moment: float) -> None:
        """The bus is up at ``moment``: after quick losses, once up ``STABLE_S``, it is said
        (rule 3). Cheap while nothing was lost: the bus thread asks at every turn."""
        if self.quick_losses and self._up_at is not None and moment - self._up_at >= STABLE_S:
            log.info(
                "bus %s up for %.0f s again, after %d losses soon after opening",
                self.bus,
                STABLE_S,
                self.quick_losses,
            )
            self.quick_losses = 0
            self._backoff = BACKOFF_FIRST_S
