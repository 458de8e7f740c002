"""The puts of one follow stream: what ``Follow.set`` does, for both faces.

Rules of this file:

1. A target is checked against the kind's follow model before anything is sent (an error now,
   not a ``command_refused`` event later), and carries the client's id; under a claim, it
   asks the gateway to refuse it unless the claim holds (``require_claim``), and it is refused
   here at once when the SDK knows the claim is lost.
2. Puts are spaced at least ``MIN_PUT_INTERVAL_S`` (the shortest follow period a device
   has): a target set sooner waits, and a newer one replaces it (latest wins, as at the
   gateway's ticks). A program that sets in a tight loop so never floods the gateway — a
   flood queued its own claim renewals behind thousands of puts until the claim lapsed.
3. No target is put twice: a program that stops setting lets the stream go stale, as it
   should (the gateway's deadman for a stream).
4. Each target carries the client's next ``seq``, taken as it is put in line, and the
   ``end_follow`` after the last one a higher one: the gateway drops a target numbered below
   the end whichever of zenoh's threads brought it late, and starts a stream at once for one
   above. A base's twist stream (``bases.py``) is numbered the same way against its ``stop``.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pydantic import ValidationError

from busgate.client.claims import ClaimLease, Timers
from busgate.client.core import Core
from busgate.client.errors import error_for
from busgate.client.messages import dumps
from busgate.schemas.validation import describe_validation_error, refusal_code

#: The shortest follow period of any device (10 ms): more puts a second only flood.
MIN_PUT_INTERVAL_S = 0.01


class FollowSender:
    """Checked, spaced puts of one device's follow targets (rules 1–3)."""

    def __init__(
        self,
        core: Core,
        timers: Timers,
        key: str,
        model: Any,
        lease_of: Any,
        what: str,
        *,
        called: str = "follow target",
    ) -> None:
        self._publish = core.publisher(key)
        self._client = core.client_id
        self._seq = core.next_seq
        self._timers = timers
        self._model = model
        self._lease_of: Any = lease_of  # () -> ClaimLease | None, looked up at each set
        self._what = what
        self._called = called  # what a target is called in the error of one that is not one
        self._lock = threading.Lock()
        self._pending: bytes | None = None
        self._armed = False
        self._next_put = 0.0
        #: Targets set, and targets put (a set may be replaced before it is put).
        self.sets = self.puts = 0

    def set(self, target: dict[str, Any]) -> None:
        lease: ClaimLease | None = self._lease_of()
        if lease is not None:
            lease.check()
        try:
            self._model.model_validate(target)
        except ValidationError as exc:
            reason = describe_validation_error(exc)
            message = f"invalid {self._called} for {self._what}: {reason}"
            raise error_for(refusal_code(exc))(message) from None
        claim = {} if lease is None else {"require_claim": True}
        with self._lock:  # numbered in the order they are put (rule 4)
            payload = dumps({**target, **claim, "client": self._client, "seq": self._seq()})
            self.sets += 1
            if self._armed or time.monotonic() < self._next_put:
                self._pending = payload
                if not self._armed:
                    self._armed = True
                    self._timers.at(self._next_put, self._flush)
                return
            self._put(payload)

    def close(self) -> None:
        """Put the last target still waiting, then undeclare the publisher."""
        with self._lock:
            payload, self._pending = self._pending, None
            if payload is not None:
                self._put(payload)
        self._publish.undeclare()  # type: ignore[attr-defined]

    def _flush(self) -> None:
        """The timer thread: the latest target that waited."""
        with self._lock:
            self._armed = False
            payload, self._pending = self._pending, None
            if payload is not None:
                self._put(payload)

    def _put(self, payload: bytes) -> None:
        self._next_put = time.monotonic() + MIN_PUT_INTERVAL_S
        self.puts += 1
        self._publish(payload)
