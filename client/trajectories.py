"""Trajectories a gateway plays for this client: the ``play`` request, and what the gateway
says of it afterwards (feedback, then one result), for both faces of the SDK.

Rules: the feedback key is subscribed before ``play`` is sent, so a result that comes at once
is not missed, as any sample's JSON (``base.Shared.subscribe``: none past what a gateway
publishes there);
the zenoh callback only stores a message and wakes the readers (their sinks may not block); a
trajectory's devices are found by name like any device, and must all be on one gateway.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from typing import Any

from busgate.client.base import Shared
from busgate.client.core import closed_reading
from busgate.client.errors import NoAnswerError
from busgate.client.faces import Face, feeding, waiting
from busgate.client.feeds import Inbox
from busgate.client.messages import MAX_WAIT_S, seconds, then
from busgate.client.steps import Items, Next, Steps, Wait
from busgate.errors import BusgateError, CommandError

_ids = itertools.count(1)

#: The fields of a ``play`` besides devices and points, as the SDK's ``play`` names them
#: (``units``: ``"joint"`` for SI positions, velocities, accelerations and tolerances; left
#: out, the devices' raw units).
PLAY_OPTIONS = (
    "start_at",
    "interpolation",
    "path_tolerance",
    "goal_tolerance",
    "goal_time_s",
    "units",
)


def one_gateway(found: list[Any]) -> str:
    """The one gateway of a trajectory's devices (``CommandError`` when they are on several:
    each gateway plays its own)."""
    gateways = sorted({device.gateway for device in found})
    if len(gateways) != 1:
        raise CommandError(
            f"a trajectory plays the devices of one gateway, not of {', '.join(gateways)}: "
            "play one trajectory per gateway, with the same start_at"
        )
    return gateways[0]


def result_wait_s(end_at: float, timeout: float | None) -> float:
    """How long to wait for a result: ``timeout`` (``CommandError`` unless a number of
    seconds from 0 to ``MAX_WAIT_S``: infinity overflowed the wait), or until 30 s past
    ``end_at``."""
    if timeout is not None:
        return seconds("timeout", timeout, 0, MAX_WAIT_S)
    return max(1.0, end_at - time.time() + 30.0)


def play_body(
    client_id: str,
    trajectory_id: str | None,
    devices: list[str],
    points: list[dict[str, Any]],
    options: dict[str, Any],
) -> dict[str, Any]:
    """The ``play`` command (``None`` options left out: without ``units``, a play in the
    devices' raw units, its payload as it always was)."""
    chosen = trajectory_id or f"{client_id}-{os.getpid()}-{next(_ids)}"
    given = {name: options[name] for name in PLAY_OPTIONS if options.get(name) is not None}
    return {"op": "play", "id": chosen, "devices": devices, "points": points, **given}


class Watch:
    """What a gateway says of one trajectory: each feedback message, then its result."""

    def __init__(self, shared: Shared, gateway: str, trajectory_id: str) -> None:
        self.gateway = gateway
        self.id = trajectory_id
        self._lock = threading.Lock()
        self._inboxes: list[Inbox[dict[str, Any]]] = []
        self.result: dict[str, Any] | None = None
        self.finished: Future = Future()
        self._closed = False  # by ``close``: the client may still be open
        self._ended_with: Exception | None = None  # the subscription's end: what a reader meets
        self._stop_listening = shared.core.on_gateway_gone(self._gateway_gone)
        key = shared.core.keys.feedback(gateway, trajectory_id)
        self._end = shared.subscribe(key, self._on_message, lambda: self._ended(key))

    def add_inbox(self, inbox: Inbox[dict[str, Any]]) -> Callable[[], None]:
        """Each message from now on to ``inbox``, which ends with the client (its reader
        meets ``session closed``); returns what removes it."""
        with self._lock:
            if self._ended_with is not None:
                inbox.end(self._ended_with)
            self._inboxes.append(inbox)

        def remove() -> None:
            with self._lock:
                if inbox in self._inboxes:
                    self._inboxes.remove(inbox)

        return remove

    def close(self) -> None:
        self._closed = True
        self._stop_listening()
        self._end()

    def _on_message(self, key: str, message: Any) -> None:
        if not isinstance(message, dict):  # not JSON, or past what a gateway publishes
            return
        with self._lock:
            inboxes = list(self._inboxes)
            if "result" in message and self.result is None:
                self.result = message
        for inbox in inboxes:
            inbox.put(message)
        if "result" in message:
            self._stop_listening()  # its gateway's going is no news to it now
            with contextlib.suppress(InvalidStateError):  # it went first
                self.finished.set_result(message)

    def _gateway_gone(self, gateway: str) -> None:
        """The gateway's token went: a result still to come never will (a restarted gateway
        plays nothing it played before). A wait for it ended only at its timeout, told as
        "no answer" (an audit: 35 s after a restart the client itself knew of at once)."""
        if gateway == self.gateway and self.result is None:
            self._end_waits(
                NoAnswerError(
                    f"trajectory {self.id}: gateway {gateway} went away (restarted or cut "
                    "off) before its result came"
                )
            )

    def _ended(self, key: str) -> None:
        """The subscription ended (the client closed, or the watch): a wait for the result
        or the feedback, under way or to come, meets ``session closed``, or that the watch
        was closed."""
        self._stop_listening()
        self._end_waits(
            CommandError(f"trajectory {self.id} is no longer listened to: closed")
            if self._closed
            else closed_reading(key)
        )

    def _end_waits(self, why: Exception) -> None:
        with self._lock:
            self._ended_with = why
            inboxes = list(self._inboxes)
        for inbox in inboxes:
            inbox.end(why)
        with contextlib.suppress(InvalidStateError):
            self.finished.set_exception(why)


class Handle(Face):
    """What both faces' ``Trajectory`` are: a trajectory a gateway plays for this client, its
    ``id``, ``gateway``, ``devices``, ``start_at`` and ``end_at`` (wall clock, as telemetry's
    ``ts``), and what the gateway said of it."""

    def __init__(self, shared: Shared, watch: Watch, accepted: dict[str, Any]) -> None:
        self._shared, self._watch = shared, watch
        self.id, self.gateway = watch.id, watch.gateway
        self.devices: list[str] = accepted["devices"]
        self.start_at: float = accepted["start_at"]
        self.end_at: float = accepted["end_at"]

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.gateway}/{self.id} {self.devices}>"

    @property
    def result(self) -> dict[str, Any] | None:
        """The result message once it came (``result``, ``reason``, ``errors``), else None."""
        return self._watch.result

    def close(self) -> None:
        """Stop listening to the trajectory (it plays on); a wait for its result or its
        feedback under way ends, with ``CommandError``."""
        self._watch.close()

    def _left(self, failed: bool) -> None:
        """The ``with`` block's end: ``close``; first, when an exception ended it (a Ctrl-C,
        the program's own error) and the trajectory has no result yet, a cancel, sent without
        waiting for its answer, as a follow stream's block ends its stream: the devices do
        not play on for as long as the client stays open (a notebook, a program that goes on
        after its ``except``)."""
        try:
            if failed and self.result is None:
                with contextlib.suppress(BusgateError):  # a closed client: its going ends it
                    send_cancel(self._shared, self.gateway, self.id, self._shared.core.timeout_s)
        finally:  # a second Ctrl-C in the cancel still stops the listening
            self.close()

    @waiting
    def wait(self, timeout: float | None = None) -> Steps[dict[str, Any]]:
        """The result (``{"result": "succeeded" | "canceled" | "replaced" | "aborted",
        "reason"?, "errors"}``); by default waits until 30 s past ``end_at``."""
        waited = result_wait_s(self.end_at, timeout)
        result = Wait(self._watch.finished, waited, f"the result of trajectory {self.id}", 0.0)
        return (yield result)  # no query's margin: the result comes on a subscription

    @waiting
    def cancel(self, *, timeout: float | None = None) -> Steps[dict[str, Any]]:
        """Each device decelerates to a stop and holds; the result is ``canceled``."""
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = send_cancel(self._shared, self.gateway, self.id, waited)
        return (yield Wait(sent, waited, f"cancel of trajectory {self.id}"))

    @feeding
    def feedback(self, timeout: float | None = None) -> Items[dict[str, Any]]:
        """Each feedback message as it comes (``t_s``, per device ``desired``,
        ``commanded``, ``measured``, ``error`` in raw units, and ``joint``: the same in its
        joint's SI ``unit``), until the result or ``timeout``."""
        deadline = time.monotonic() + result_wait_s(self.end_at, timeout)
        inbox: Inbox[dict[str, Any]] = Inbox()
        remove = self._watch.add_inbox(inbox)
        try:
            while self._watch.result is None and (left := deadline - time.monotonic()) > 0:
                message = yield Next(inbox.next(), left)
                if message is None or "result" in message:
                    return
                yield message
        finally:
            remove()


def start(shared: Shared, gateway: str, body: dict[str, Any], timeout_s: float) -> Future:
    """Watch, then send ``play``: a future of (``Watch``, the reply's ``trajectory``)."""
    watch = Watch(shared, gateway, body["id"])
    try:
        sent = shared.core.command(shared.core.keys.trajectory(gateway), body, timeout_s=timeout_s)
    except BaseException:  # refused before it was sent (over 2 MiB): nothing to watch
        watch.close()
        raise

    def accepted(reply: dict[str, Any]) -> tuple[Watch, dict[str, Any]]:
        return watch, reply["trajectory"]

    def refused(done: Future) -> None:
        if done.exception() is not None:
            watch.close()

    chained = then(sent, accepted)
    chained.add_done_callback(refused)
    return chained


def send_cancel(shared: Shared, gateway: str, trajectory_id: str, timeout_s: float) -> Future:
    key = shared.core.keys.trajectory(gateway)
    return shared.core.command(key, {"op": "cancel", "id": trajectory_id}, timeout_s=timeout_s)
