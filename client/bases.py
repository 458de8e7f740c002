"""A base of a gateway (``[[bases]]``: two ZLAC706 hub motors driven as one differential
drive), of either face: ``Client.base``, each method written once (``steps.py``) as a
device's are (``devices.py``).

Rules of this file:

1. A base is found by its own key, not by ``info`` (which lists no bases): a ``status`` on
   ``<p>/<gw>/base/<name>/cmd``. ``"gw/name"`` asks that gateway (which answers
   ``unknown_device`` when it has no such base); a bare name asks every gateway at once
   (``<p>/*/base/<name>/cmd``: a gateway answers a query with a wildcard only for a base it
   has) and must be one gateway's (``AmbiguousError`` naming them, as for a device).
2. Its commands are sent as a device's (``base.Shared.send``): with the client's id, and
   under this client's claim of the base with ``require_claim``; a refusal is raised as its
   class (``bc.error_for(code)``). Each gives the base's status: the reply's ``base``.
3. Its claim is a device's (``ClaimBase``; ``claims.ClaimLease`` on the base's command key):
   taken on entry, renewed in the background, given back on exit or at ``release``, and gone
   with the client's liveliness token; the gateway takes both wheels or neither.
4. A drive stream puts each twist on ``…/twist`` as a follow stream puts its targets
   (``follow.FollowSender``: checked here against ``TwistTarget``, spaced, latest wins, under
   a claim ``require_claim``), each numbered (``seq``). Its end sends ``stop`` numbered after
   them and waits for the reply: the gateway takes puts and queries on different threads,
   and drops a twist numbered below its client's stop whenever it comes.
5. Odometry (``…/odom``) is read as ``Odometry`` (``schemas.bases``): the latest
   (``feeds.Latest``, as a device's state) or each as it comes; a message that is not one,
   or names another base, is left out with a warning, as a joints message is.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, Self, TypeVar

from busgate.client.base import Found, Shared
from busgate.client.devices import StreamBase, last_exchange
from busgate.client.errors import (
    AmbiguousError,
    GatewayError,
    NoAnswerError,
    error_for,
)
from busgate.client.faces import Face, feeding, waiting
from busgate.client.feeds import latest_parsed, parsed_feed
from busgate.client.follow import FollowSender
from busgate.client.keys import Keys, split_name
from busgate.client.messages import (
    Answers,
    Odometry,
    dumps,
    first_ok,
    published_naming,
    then,
)
from busgate.client.steps import Items, Steps, Wait
from busgate.schemas.bases import TwistTarget

#: The kind of every base a gateway has (``[[bases]]``' ``kind``).
KIND = "diff_drive"

Claim = TypeVar("Claim")
DriveStream = TypeVar("DriveStream")


def find_base(shared: Shared, name: str, timeout_s: float) -> Future:
    """A future of the base ``name`` (``"gw/base"`` or a bare ``"base"``, rule 1): its
    ``Found`` and the status its gateway answered."""
    gateway, leaf = split_name(name, "base")
    core = shared.core
    key = core.keys.base(gateway or "*", leaf, "cmd")
    asked = core.ask(key, dumps({"op": "status", "client": core.client_id}), timeout_s=timeout_s)
    return then(
        asked,
        lambda answers: located(
            answers, gateway, leaf, key, timeout_s, core.keys, set(core.gateways_up)
        ),
    )


def located(
    answers: Answers,
    gateway: str | None,
    leaf: str,
    asked: str,
    timeout_s: float,
    keys: Keys,
    up: set[str],
) -> tuple[Found, dict[str, Any]]:
    """The one base among the answers to a ``status`` on ``asked`` (rule 1), and its status.
    Nobody answering a bare name while gateways are up: ``UnknownDeviceError`` naming them."""
    found = [answer for answer in answers if answer.ok]
    if not found:
        if gateway is None and not answers and not answers.timed_out and up:
            raise error_for("unknown_device")(
                f"no base {leaf!r} on the gateways up ({', '.join(sorted(up))}): none "
                f"answered on {asked}"
            )
        first_ok(answers, asked, timeout_s, gateway)  # the refusal, or nobody answered
    if len(found) > 1:
        names = sorted(keys.gateway_of(answer.key) for answer in found)
        raise AmbiguousError(
            f"{len(found)} gateways have a base {leaf!r} ({', '.join(names)}): name one, "
            f"e.g. {names[0]}/{leaf}",
            gateways=names,
        )
    answer = found[0]
    at = keys.gateway_of(answer.key)
    return Found(at, leaf, KIND, room="base"), status_of(answer.body, f"base {at}/{leaf}")


def status_of(reply: Any, where: str) -> dict[str, Any]:
    """The base's status an ok reply carries (its ``base``)."""
    status = reply.get("base") if isinstance(reply, dict) else None
    if not isinstance(status, dict):
        raise GatewayError(f"the reply of {where} carries no base status: {str(reply)[:200]}")
    return status


class MobileBase(Face, Generic[Claim, DriveStream]):
    """One base of one gateway (``Client.base``), of either face: two ZLAC706 wheels driven
    as one differential drive. ``gateway`` and ``name``, and ``wheels``: its left and right
    devices, as its status named them when it was found."""

    _Claim: Callable[[Shared, Found, float], Claim]
    _DriveStream: Callable[[Shared, Found], DriveStream]

    def __init__(self, shared: Shared, found: Found, status: dict[str, Any]) -> None:
        self._shared, self._found = shared, found
        self.name, self.gateway = found.name, found.gateway
        wheels = status.get("wheels")
        self.wheels: tuple[str, ...] = (
            tuple(str(wheel) for wheel in wheels) if isinstance(wheels, list) else ()
        )

    def __repr__(self) -> str:
        return f"<{self._prefix}Base {self.gateway}/{self.name} ({', '.join(self.wheels)})>"

    def _where(self) -> str:
        return f"base {self.gateway}/{self.name}"

    def _sending(self, command: dict[str, Any]) -> Steps[dict[str, Any]]:
        waited = self._shared.core.timeout_s
        sent = self._shared.send(self._found, command, waited)
        reply = yield Wait(sent, waited, f"{command['op']} on {self._where()}")
        return status_of(reply, self._where())

    @waiting
    def status(self) -> Steps[dict[str, Any]]:
        """The base's status: ``name``, ``wheels``, ``driving`` (its wheels play a twist),
        ``client`` (whose twist it last took), ``twist`` (the one its wheels were last sent:
        ``linear``, ``angular``) and ``odometry`` (``x``, ``y``, ``theta``)."""
        return (yield from self._sending({"op": "status"}))

    @waiting
    def enable(self) -> Steps[dict[str, Any]]:
        """Both wheels on, in velocity mode (both power stages together): the base's status.
        A twist to a base whose wheels are off is refused (``BadCommandError``)."""
        return (yield from self._sending({"op": "enable"}))

    @waiting
    def disable(self) -> Steps[dict[str, Any]]:
        """Both power stages off (a twist under way is stopped first): the base's status."""
        return (yield from self._sending({"op": "disable"}))

    @waiting
    def drive(
        self, linear: float, angular: float = 0.0, duration_s: float | None = None
    ) -> Steps[dict[str, Any]]:
        """Drive at ``linear`` m/s and ``angular`` rad/s (counter-clockwise positive), scaled
        down to the base's limits keeping the curvature, for its ``cmd_timeout_s`` (or
        ``duration_s``, at most 10 s), then ramped to 0: the base's status, with the twist
        it took as ``target``. Refused as a device's command is (``ClaimedError``,
        ``EstoppedError``, ``BadCommandError`` for wheels that are off …)."""
        command: dict[str, Any] = {"op": "twist", "linear": linear, "angular": angular}
        if duration_s is not None:
            command["duration_s"] = duration_s
        return (yield from self._sending(command))

    @waiting
    def stop(self) -> Steps[dict[str, Any]]:
        """Ramp to 0 at the base's deceleration limits now (never refused): its status."""
        return (yield from self._sending({"op": "stop"}))

    @waiting
    def reset_odometry(self) -> Steps[dict[str, Any]]:
        """The pose back to (0, 0, 0) from the wheels' next reading: the base's status."""
        return (yield from self._sending({"op": "reset_odometry"}))

    def claim(self, ttl_s: float = 60.0) -> Claim:
        """Both wheels for this client while the ``with`` block runs, as one claim (the
        gateway takes both or neither, ``ClaimedError`` naming the holder of either): claimed
        on entry, renewed before ``ttl_s`` lapses, released on exit (``ClaimLostError`` on
        exit, and on any twist meanwhile, if it was lost); it goes with the client."""
        return self._Claim(self._shared, self._found, ttl_s)

    @waiting
    def release(self) -> Steps[dict[str, Any]]:
        """Give this client's claim of the base back now: a ``claim`` block's renewals stop
        (its exit has nothing left to give back), else ``{"op": "release"}`` is sent; the
        base's status. ``ClaimLostError`` when the block's claim was lost."""
        lease = self._shared.lease_of(self._found)
        if lease is None:
            return (yield from self._sending({"op": "release"}))
        released = self._shared.unclaim(lease)
        reply = yield Wait(released, self._shared.core.timeout_s, f"release of {self._where()}")
        return status_of(reply, self._where())

    def drive_stream(self) -> DriveStream:
        """A twist stream while the ``with`` block runs: ``send(linear, angular)`` puts the
        base's new twist on its ``twist`` key (latest wins); the base holds each for its
        ``cmd_timeout_s``, then ramps to 0 (``stream_stale``), so keep sending. On exit the
        base is stopped at once (``stop``, numbered after the last twist: one of the block's
        that reaches the gateway later is dropped), not after its timeout."""
        return self._DriveStream(self._shared, self._found)

    def _odometry_key(self) -> str:
        return self._shared.core.keys.base(self.gateway, self.name, "odom")

    def _message(self, payload: bytes | None) -> Odometry | None:
        if payload is None:
            return None
        what = f"odometry messages of base {self.name!r}"
        return published_naming(Odometry, payload, what, self.gateway, "base", self.name)

    @waiting
    def odometry(self, timeout: float = 2.0, *, max_age: float = 1.0) -> Steps[Odometry]:
        """The base's latest odometry (``x``, ``y``, ``theta``, ``linear``, ``angular``,
        ``ts``): one received in the last ``max_age`` seconds, else the next within
        ``timeout`` (it comes as the wheels are read)."""
        latest = self._shared.latest(self._odometry_key(), self.gateway, timeout, max_age)
        message = yield from latest_parsed(latest, self._message, timeout, max_age)
        if message is None:
            raise NoAnswerError(f"no odometry of {self._where()} within {timeout:g} s")
        return message

    @feeding
    def odometry_feed(self, timeout: float = 5.0) -> Items[Odometry]:
        """Each new odometry message of the base, as it comes, until ``timeout`` seconds."""
        core, key = self._shared.core, self._odometry_key()
        yield from parsed_feed(core, key, self._message, timeout)


class DriveStreamBase(StreamBase):
    """A base's twist stream held by a block (``Base.drive_stream``), of either face."""

    _model = TwistTarget
    _setter, _called = "send", "drive stream"

    def _opened(self) -> Self:
        """Open the stream (the block's entry)."""
        shared, found = self._shared, self._found
        self._sender = FollowSender(
            shared.core,
            shared.timers,
            shared.core.keys.base(found.gateway, found.name, "twist"),
            self._model,
            lambda: shared.lease_of(found),
            f"base {found.gateway}/{found.name}",
            called="twist",
        )
        return self

    def send(self, linear: float, angular: float = 0.0) -> None:
        """The base's new twist, ``linear`` m/s and ``angular`` rad/s, latest winning:
        checked here (``BadCommandError``: not a number), put at most every 10 ms. Does not
        wait: a refusal (wheels off, a claim of another client) is the gateway's
        ``command_refused`` event."""
        self._put({"linear": linear, "angular": angular})

    def _ended(self, kind: type[BaseException] | None) -> Steps[None]:
        """``stop``, numbered after the last twist (the block's exit, rule 4)."""
        sender, self._sender = self._sender, None
        assert sender is not None
        sender.close()
        where = f"{self._found.gateway}/{self._found.name}"
        stop = {"op": "stop", "seq": self._shared.core.next_seq()}
        stopped = self._shared.send(self._found, stop, None)
        yield from last_exchange(self._shared, stopped, kind, f"stop of base {where}")
