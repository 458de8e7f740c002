"""Claims that stay held while a program runs: renewed in the background before their TTL
lapses, and reported when they are lost (as Boston Dynamics' lease keep-alive does).

Rules of this file:

1. A claim is renewed every third of its TTL, so one lost renewal never lets it lapse.
2. A claim is lost, never silently re-taken, when a renewal is refused (another client took
   the device after a lapse), when no renewal was answered before the TTL ran out, or when
   its gateway's liveliness token went (the gateway restarted or is cut off: its claims went
   with it). Motion through a lost claim raises ``ClaimLostError`` until the program claims
   again.
3. Renewals run on one timer thread per client; what they do there is send a query, never
   wait for one (the reply settles on zenoh's thread).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from busgate.client.core import Core
from busgate.client.errors import ClaimedError, ClaimLostError, GatewayError
from busgate.client.messages import seconds, then
from busgate.schemas.api import MAX_CLAIM_S

log = logging.getLogger(__name__)

#: The shortest claim renewed in the background (a renewal every 0.1 s), and the longest the
#: gateway grants.
MIN_TTL_S = 0.3


class Timers:
    """Calls functions at monotonic times, on one daemon thread (started on first use): the
    claims' renewals and the follow streams' spaced puts."""

    def __init__(self) -> None:
        self._due: list[tuple[float, int, Callable[[], None]]] = []
        self._count = itertools.count()
        self._changed = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False

    def at(self, when: float, function: Callable[[], None]) -> None:
        with self._changed:
            if self._closed:
                return
            heapq.heappush(self._due, (when, next(self._count), function))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="busgate-client-timers")
                self._thread.daemon = True
                self._thread.start()
            self._changed.notify()

    def close(self) -> None:
        with self._changed:
            self._closed = True
            self._due.clear()
            self._changed.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    def _run(self) -> None:
        while True:
            with self._changed:
                while not self._closed and (not self._due or self._due[0][0] > time.monotonic()):
                    wait = self._due[0][0] - time.monotonic() if self._due else None
                    self._changed.wait(wait)
                if self._closed:
                    return
                _, _, function = heapq.heappop(self._due)
            try:
                function()
            except Exception:  # one failed renewal or put must not stop the others
                log.exception("a client timer failed")


class ClaimLease:
    """This client's claim on one device of one gateway, or on one of its bases: what its
    command key (``key``, the device's unless given) takes ``claim`` and ``release`` on."""

    def __init__(
        self,
        core: Core,
        timers: Timers,
        gateway: str,
        device: str,
        ttl_s: float,
        key: str | None = None,
    ):
        seconds("ttl_s", ttl_s, MIN_TTL_S, MAX_CLAIM_S)
        self.core = core
        self.timers = timers
        self.gateway = gateway
        self.device = device
        self.ttl_s = ttl_s
        self.key = core.keys.device(gateway, device, "cmd") if key is None else key
        #: Why the claim was lost (``None`` while it is held).
        self.lost: str | None = None
        self._held_until = 0.0
        self._ended = False
        self._stop_listening = core.on_gateway_gone(self._gateway_gone)

    def take(self) -> Future:
        """Claim now (the future: the reply, or ``ClaimedError``); renewals follow."""
        asked = time.monotonic()
        claimed = self.core.command(self.key, {"op": "claim", "ttl_s": self.ttl_s})
        return then(claimed, lambda reply: self._held(reply, asked))

    def check(self) -> None:
        """``ClaimLostError`` when the claim was lost (rule 2)."""
        if self.lost is not None:
            raise ClaimLostError(f"the claim on {self.gateway}/{self.device} was lost: {self.lost}")

    def lost_error(self, refusal: BaseException) -> BaseException:
        """The gateway's refusal of a command sent under this claim, as ``ClaimLostError``
        (with why) when the claim is known lost and the gateway refused for want of it."""
        if self.lost is None or not isinstance(refusal, ClaimedError | ClaimLostError):
            return refusal
        where = f"{self.gateway}/{self.device}"
        return ClaimLostError(
            f"the claim on {where} was lost: {self.lost} (the gateway: {refusal})",
            gateway=self.gateway,
        )

    @property
    def ended(self) -> bool:
        """Whether it was given back (``release``): nothing renews it any more."""
        return self._ended

    def release(self) -> Future | None:
        """Stop renewing and give the claim back (nothing to give when it was lost, or was
        given back already)."""
        if self._ended:
            return None
        self._ended = True
        self._stop_listening()
        if self.lost is not None:
            return None
        return self.core.command(self.key, {"op": "release"})

    # -- renewals (the timer thread and zenoh's threads) --------------------------------------

    def _held(self, reply: Any, asked: float) -> Any:
        self._held_until = asked + self.ttl_s
        self.timers.at(asked + self.ttl_s / 3, self._renew)
        return reply

    def _renew(self) -> None:
        if self._ended or self.lost is not None:
            return
        if time.monotonic() >= self._held_until:
            self._lose(f"no renewal was answered within its TTL of {self.ttl_s:g} s")
            return
        asked = time.monotonic()
        try:
            renewed = self.core.command(
                self.key, {"op": "claim", "ttl_s": self.ttl_s}, timeout_s=self.ttl_s / 3
            )
        except Exception as exc:  # the session closed under the timer: nothing to renew
            self._lose(f"the renewal could not be sent ({exc})")
            return
        renewed.add_done_callback(lambda done: self._renewed(done, asked))

    def _renewed(self, done: Future, asked: float) -> None:
        error = done.exception()
        if error is None:
            self._held(done.result(), asked)
        elif isinstance(error, GatewayError):
            self._lose(f"the gateway refused to renew it: {error.code}: {error}")
        else:  # nobody answered: try again; rule 2 decides once the TTL is out
            self.timers.at(time.monotonic() + self.ttl_s / 6, self._renew)

    def _gateway_gone(self, gateway: str) -> None:
        if gateway == self.gateway and not self._ended:
            self._lose(f"gateway {gateway} went away (restarted or cut off)")

    def _lose(self, reason: str) -> None:
        if self.lost is None:
            self.lost = reason
