"""What a device, a bus, a claim and a follow stream of either face are and do, each method
written once (``steps.py``); ``Claim``, ``Follow`` and ``Joint`` here are type variables, each
face's own classes (``Device.claim`` of the blocking face is a ``bc.Claim``, of the asyncio face
a ``bc.aio.Claim``). A face's module adds only the ways into and out of a block (``with`` or
``async with``). A device's joint is ``joints.py``'s.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, Self, TypeVar

from busgate.client.base import Found, Shared, as_body, reenable_command, scan_command
from busgate.client.claims import ClaimLease
from busgate.client.errors import NoAnswerError, error_for
from busgate.client.faces import Face, feeding, waiting
from busgate.client.feeds import parsed_feed
from busgate.client.follow import FollowSender
from busgate.client.steps import Items, Next, Steps, Wait
from busgate.errors import BusgateError, CommandError

Claim = TypeVar("Claim")
Follow = TypeVar("Follow")
Joint = TypeVar("Joint")


class DeviceBase(Face, Generic[Claim, Follow, Joint]):
    """One device of one gateway, of either face."""

    _Claim: Callable[[Shared, Found, float], Claim]
    _Follow: Callable[[Shared, Found], Follow]
    _Joint: Callable[[Any], Joint]

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared = shared
        self._found = found
        self.name, self.gateway, self.kind = found.name, found.gateway, found.kind
        self._joint: Joint | None = None

    def __repr__(self) -> str:
        return f"<{self._prefix}Device {self.gateway}/{self.name} ({self.kind})>"

    def _sending(self, command: Any, timeout: float | None) -> Steps[dict[str, Any]]:
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.send(self._found, command, waited)
        return (yield Wait(sent, waited, f"{as_body(command).get('op')} on {self._where()}"))

    def _where(self) -> str:
        return f"{self.gateway}/{self.name}"

    @waiting
    def send(self, command: Any, *, timeout: float | None = None) -> Steps[dict[str, Any]]:
        """Send a command (a dict, or a model of ``busgate.schemas``); the reply's body, or
        the error it carries raised as its class (``bc.error_for(code)``)."""
        return (yield from self._sending(command, timeout))

    @waiting
    def move(self, position: int, **fields: Any) -> Steps[dict[str, Any]]:
        """Move to ``position`` (the kind's units); ``fields`` add to the ``move`` op."""
        return (yield from self._sending({"op": "move", "position": position, **fields}, None))

    @waiting
    def velocity(self, rpm: float) -> Steps[dict[str, Any]]:
        """Turn at ``rpm`` (a ZLAC706 in velocity mode)."""
        return (yield from self._sending({"op": "velocity", "rpm": rpm}, None))

    @waiting
    def enable(self) -> Steps[dict[str, Any]]:
        """Let the device move again after an e-stop (its kind's re-enable command)."""
        return (yield from self._sending(reenable_command(self.kind), None))

    @waiting
    def reset_estop(self) -> Steps[dict[str, Any]]:
        """Out of the gateway's e-stop, back in the power state the device had before it and
        holding still: nothing moves until a new command (``{"op": "reset_estop"}``, as
        ``send`` sends it)."""
        return (yield from self._sending({"op": "reset_estop"}, None))

    @property
    def joint(self) -> Joint:
        """The device as a joint, in SI units: its name, type, unit, calibration and limits
        as its gateway's ``info`` describes them, its state, and its moves and streams."""
        if self._joint is None:
            self._joint = self._Joint(self)
        return self._joint

    @waiting
    def state(self, timeout: float = 2.0, *, max_age: float = 1.0) -> Steps[Any]:
        """The device's latest telemetry, as its kind's model: one received in the last
        ``max_age`` seconds, else the next to come within ``timeout``."""
        return (yield from self._latest_state(timeout, max_age))

    def _latest_state(self, timeout: float, max_age: float) -> Steps[Any]:
        latest = self._shared.latest(self._state_key(), self.gateway, timeout, max_age)
        payload = latest.recent(max_age)
        if payload is None:
            payload = yield Next(latest.next(), timeout)
        if payload is None:
            raise NoAnswerError(f"no state of {self._where()} within {timeout:g} s")
        state = self._state(payload)
        if state is None:  # left out, the warning says why; told, not waited past (sdk.md)
            raise error_for("internal")(
                f"the state on the key of {self._where()} is not one its {self._found.kind} sends"
            )
        return state

    @feeding
    def states(self, timeout: float = 5.0) -> Items[Any]:
        """Each new state message of the device, as it comes, until ``timeout`` seconds."""
        yield from parsed_feed(self._shared.core, self._state_key(), self._state, timeout)

    def _state_key(self) -> str:
        return self._shared.core.keys.device(self.gateway, self.name, "state")

    def _state(self, payload: bytes) -> Any:
        """A state message of the device, as its kind's model; ``None`` for one that is not
        (left out, the warning says why)."""
        return self._shared.telemetry(self._found, payload)

    def claim(self, ttl_s: float = 2.0) -> Claim:
        """Exclusive motion control while the ``with`` block runs: claimed on entry,
        renewed before ``ttl_s`` lapses, released on exit (``ClaimLostError`` on exit, and on
        any motion meanwhile, if it was lost)."""
        return self._Claim(self._shared, self._found, ttl_s)

    def follow(self) -> Follow:
        """A follow stream while the ``with`` block runs: ``set(**target)`` with the fields
        of the follow target of the device's kind (``busgate.schemas``' ``FollowTarget``:
        ``position=…`` for an Inspire LA); the latest target is sent at the device's period;
        the stream ends (``end_follow``) when the block exits. In SI: ``joint.follow()``."""
        return self._Follow(self._shared, self._found)


class BusBase(Face):
    """One bus of one gateway, of either face."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self.name, self.gateway, self.protocol = found.name, found.gateway, found.kind

    def __repr__(self) -> str:
        return f"<{self._prefix}Bus {self.gateway}/{self.name} ({self.protocol})>"

    def _sending(self, command: dict[str, Any], timeout: float | None) -> Steps[dict[str, Any]]:
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.bus_command(self._found, command, waited)
        what = f"{command.get('op')} on bus {self.gateway}/{self.name}"
        return (yield Wait(sent, waited, what))

    @waiting
    def send(
        self, command: dict[str, Any], *, timeout: float | None = None
    ) -> Steps[dict[str, Any]]:
        """A bus command (``group_move``, ``scan``); the reply's body, or its error raised."""
        return (yield from self._sending(command, timeout))

    @waiting
    def group_move(
        self, targets: list[dict[str, Any]], *, timeout: float | None = None
    ) -> Steps[dict[str, Any]]:
        """Start several devices of the bus together: ``[{"device": "la1", "position": 100},
        …]`` (``time_ms`` per target on a DS bus)."""
        return (yield from self._sending({"op": "group_move", "targets": targets}, timeout))

    @waiting
    def scan(
        self, ids: list[int] | None = None, *, timeout: float | None = None
    ) -> Steps[list[Any]]:
        """Which ids answer on the bus (all of the protocol's when ``ids`` is None), and as
        what."""
        found = (yield from self._sending(scan_command(ids), timeout)).get("found")
        if not isinstance(found, list):
            raise error_for("internal")(
                f"the scan of bus {self.gateway}/{self.name} answered no list of ids"
            )
        return found


def last_exchange(
    shared: Shared, future: Future, kind: type[BaseException] | None, what: str
) -> Steps[None]:
    """Wait for a block's last exchange; its failure is raised unless the block is already
    raising (that exception says more)."""
    try:
        yield Wait(future, shared.core.timeout_s, what)
    except Exception:
        if kind is None:
            raise


class ClaimBase(Face):
    """A claim held by a block (``Device.claim``, ``Base.claim``), of either face."""

    def __init__(self, shared: Shared, found: Found, ttl_s: float) -> None:
        self._shared, self._found, self.ttl_s = shared, found, ttl_s
        self._lease: ClaimLease | None = None

    @property
    def lost(self) -> str | None:
        """Why the claim was lost, or ``None`` while it holds."""
        return None if self._lease is None else self._lease.lost

    def _taken(self) -> Steps[Self]:
        """Claim (the block's entry); given back at once when that fails or is cancelled."""
        lease = self._shared.claim(self._found, self.ttl_s)
        what = f"claim of {self._found.gateway}/{self._found.name}"
        try:
            yield Wait(lease.take(), self._shared.core.timeout_s, what)
        except BaseException:
            self._shared.unclaim(lease)
            raise
        self._lease = lease
        return self

    def _given_back(self, kind: type[BaseException] | None) -> Steps[None]:
        """Release the claim (the block's exit). A base's block that an exception ends (a
        Ctrl-C, the program's own error) stops the base first, without waiting for the
        answer: a one-shot drive's ``duration_s`` ran on after the release, up to 10 s."""
        lease, self._lease = self._lease, None
        assert lease is not None
        if kind is not None and self._found.room == "base":
            stop = {"op": "stop", "seq": self._shared.core.next_seq()}
            with contextlib.suppress(BusgateError):  # a closed client: its going stops it
                self._shared.send(self._found, stop, None)
        released = self._shared.unclaim(lease)
        yield from last_exchange(self._shared, released, kind, f"release of {lease.device}")


class OutsideBlockError(CommandError, RuntimeError):
    """A stream's ``set()`` or ``send()`` outside its block: a ``CommandError``, as every
    refusal of the SDK's is a ``BusgateError``, and the ``RuntimeError`` it was before, for
    the programs that caught that."""


class StreamBase(Face):
    """A stream of targets held by a block, of either face: a device's follow stream
    (``FollowBase``), a joint's (``joints.JointFollowBase``), each with its own ``set``, or a
    base's twists (``bases.DriveStreamBase``, whose ``send`` puts them)."""

    #: What each target is checked against (``None``: the follow target of the device's kind).
    _model: Any = None
    #: The stream's method that puts a target, and what the stream is called, for the error
    #: of a target put outside its block.
    _setter, _called = "set", "follow stream"

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self._sender: FollowSender | None = None

    def _opened(self) -> Self:
        """Open the stream (the block's entry)."""
        self._sender = self._shared.follow(self._found, self._model)
        return self

    @property
    def sent(self) -> int:
        """How many targets were put so far (a target replaced while it waited is not)."""
        return 0 if self._sender is None else self._sender.puts

    def _put(self, target: dict[str, Any]) -> None:
        if self._sender is None:
            raise OutsideBlockError(
                f"{self._setter}() outside the {self._called}'s {self._block} block"
            )
        self._sender.set(target)

    def _ended(self, kind: type[BaseException] | None) -> Steps[None]:
        """End the stream (the block's exit)."""
        sender, self._sender = self._sender, None
        assert sender is not None
        ended = self._shared.end_follow(self._found, sender)
        yield from last_exchange(
            self._shared, ended, kind, f"end of the stream of {self._found.name}"
        )


class FollowBase(StreamBase):
    """A device's follow stream held by a block (``Device.follow``), of either face."""

    def set(self, **target: Any) -> None:
        """The stream's new target (latest wins), the fields of the follow target of the
        device's kind (``position=…`` for an Inspire LA); checked here (``OutOfRangeError``,
        ``BadCommandError``), put at most every 10 ms."""
        self._put(target)
