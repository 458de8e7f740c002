"""The SDK's blocking face: ``connect`` → ``Client`` → ``Device`` and ``Bus``.

Each method sends through the shared core (``base.py``, ``core.py``) and waits for its future
with a timeout; every wait names what it waited for when nobody answers. Safe to use from
several threads at once (the core is; a ``Follow`` belongs to the thread that opened it).
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

from busgate.client import trajectories
from busgate.client.base import (
    WAIT_MARGIN_S,
    FleetDevice,
    Found,
    Shared,
    as_body,
    raw_payload,
    reenable_command,
    scan_command,
)
from busgate.client.claims import ClaimLease
from busgate.client.core import Answers, Core
from busgate.client.errors import NoAnswerError
from busgate.client.feeds import Latest, Stream
from busgate.client.follow import FollowSender
from busgate.client.trajectories import Handle, one_gateway, play_body, result_wait_s
from busgate.schemas.api import InfoReply

DEFAULT_TIMEOUT_S = 5.0


def wait(future: Future, timeout_s: float, what: str) -> Any:
    """The future's result (or its exception, raised), waiting at most ``timeout_s`` plus
    the margin zenoh may take to settle it."""
    try:
        return future.result(timeout_s + WAIT_MARGIN_S)
    except FutureTimeout:
        future.cancel()
        raise NoAnswerError(f"{what}: no answer within {timeout_s:g} s") from None


def connect(
    endpoints: Sequence[str] | str = "tcp/127.0.0.1:7447",
    *,
    client_id: str,
    prefix: str = "busgate",
    mode: str = "client",
    lease_s: float = 1.0,
    timeout: float = DEFAULT_TIMEOUT_S,
    config_file: str | Path | None = None,
    username: str | None = None,
    password: str | None = None,
    ca: str | Path | None = None,
) -> Client:
    """A client of every gateway reachable through ``endpoints`` (a zenoh router, or a
    gateway's own listen endpoint), as ``client_id``; use it as a context manager, or
    ``close`` it. ``lease_s``: how soon gateways give up on this client when it freezes or
    is cut off (its claims and streams go with it). ``timeout``: the default wait of every
    command. ``ConnectError`` when no session can be opened."""
    core = Core(
        endpoints,
        client_id=client_id,
        prefix=prefix,
        mode=mode,
        lease_s=lease_s,
        timeout_s=timeout,
        config_file=config_file,
        username=username,
        password=password,
        ca=ca,
    )
    return Client(Shared(core))


class Client:
    """One program's connection to a fleet of gateways."""

    def __init__(self, shared: Shared) -> None:
        self._shared = shared
        self.client_id = shared.core.client_id
        self.timeout = shared.core.timeout_s

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Release nothing explicitly (claims and streams end with the liveliness token the
        session holds) and close the session."""
        self._shared.close()

    def gateways(self, timeout: float = 1.0) -> dict[str, InfoReply]:
        """Every gateway that answers ``info`` within ``timeout``: its info, by name, as the
        model ``busgate.schemas.api.InfoReply`` (``info.buses[0].devices``; ``info["buses"]``
        too, as scripts written against the earlier release read it). A gateway whose reply
        does not validate is left out, with a warning naming it."""
        return wait(self._shared.gateways(timeout), timeout, "info of the gateways")

    def devices(self, timeout: float = 1.0) -> list[FleetDevice]:
        """Every device of the gateways ``gateways(timeout)`` gives, one ``FleetDevice`` each
        (gateway, bus, name, kind, id and last state), by gateway then name."""
        return wait(self._shared.devices(timeout), timeout, "devices of the gateways")

    def device(self, name: str, *, timeout: float | None = None) -> Device:
        """The device ``name``: ``"gw/la1"``, or a bare ``"la1"`` that one gateway has."""
        waited = self.timeout if timeout is None else timeout
        found = wait(self._shared.find(name, "device", waited), waited, f"finding {name}")
        return Device(self._shared, found)

    def bus(self, name: str, *, timeout: float | None = None) -> Bus:
        """The bus ``name``: ``"gw/uart0"``, or a bare ``"uart0"`` that one gateway has."""
        waited = self.timeout if timeout is None else timeout
        found = wait(self._shared.find(name, "bus", waited), waited, f"finding bus {name}")
        return Bus(self._shared, found)

    def on_gateways(self, callback: Callable[[str, bool], None]) -> Callable[[], None]:
        """``callback(gateway, alive)`` as each gateway comes (``True``: first for each one up
        now) and goes (``False``: its liveliness token went, as when its process ended), on
        zenoh's thread (it must not block); returns what stops it."""
        return self._shared.core.on_gateways(callback)

    def estop(self, gateway: str | None = None) -> None:
        """Stop every device of ``gateway``, or of every gateway (``None``); no gateway
        refuses it. Devices stay e-stopped until each is reset (``reset_estop``) or enabled
        again (``Device.enable``). The put goes first, never slowed by a check; then
        ``UnknownGatewayError`` when no gateway of that name is up (known at once for one
        this client has seen). Not a gateway's name (``""``): ``ValueError``, nothing sent."""
        wait(self._shared.estop(gateway), self.timeout, f"whether {gateway} is up (e-stop put)")

    def reset_estop(self, gateway: str) -> None:
        """Every device of ``gateway`` (a name: never the fleet) out of its e-stop, as
        ``Device.reset_estop``: a put of this client's id on ``<prefix>/<gateway>/estop/reset``
        (the gateway answers nothing), checked as ``estop`` checks."""
        wait(
            self._shared.reset_estop(gateway), self.timeout, f"whether {gateway} is up (reset put)"
        )

    def play(
        self,
        devices: list[str],
        points: list[dict[str, Any]],
        *,
        id: str | None = None,  # noqa: A002 - the contract's field name
        timeout: float | None = None,
        **options: Any,
    ) -> Trajectory:
        """Have the devices' gateway play a trajectory (``points`` as the trajectory key
        takes them; ``options``: ``start_at``, ``interpolation``, ``path_tolerance``,
        ``goal_tolerance``, ``goal_time_s``); the devices must be on one gateway. Returns
        once it is accepted, with its ``start_at`` and ``end_at``."""
        waited = self.timeout if timeout is None else timeout
        finding = self._shared.find_all(devices, "device", waited)
        found = wait(finding, waited, "finding the devices")
        gateway = one_gateway(found)
        body = play_body(self.client_id, id, [f.name for f in found], points, options)
        started = trajectories.start(self._shared, gateway, body, waited)
        watch, accepted = wait(started, waited, f"play of {body['id']} on {gateway}")
        return Trajectory(self._shared, watch, accepted)

    # -- raw keys (the command-line tools', and anything the typed surface lacks) ---------------

    def query(self, key: str, payload: Any = None, *, timeout: float | None = None) -> Answers:
        """Every answer to a get on the key expression ``key``, as it came (nothing added to
        the payload, no error raised for an error reply): bytes or text as given, a dict as
        JSON. ``.timed_out`` says zenoh stopped waiting for a queryable."""
        waited = self.timeout if timeout is None else timeout
        return wait(self._shared.query(key, payload, waited), waited, f"query on {key}")

    def put(self, key: str, payload: Any) -> None:
        """A put on ``key`` (bytes or text as given, a dict as JSON)."""
        self._shared.core.put(key, raw_payload(payload) or b"")

    def subscribe_raw(
        self, key: str, callback: Callable[[str, bytes, int], None]
    ) -> Callable[[], None]:
        """``callback(key, payload, ns)`` for every sample on ``key``: its bytes as they came
        and its time (ns since the epoch: zenoh's timestamp where it has one, else its
        arrival), on zenoh's thread; returns what ends the subscription (``busgate record``)."""
        return self._shared.core.subscribe_timed(key, callback)

    def subscribe(self, key: str, callback: Callable[[str, Any], None]) -> Callable[[], None]:
        """``callback(key, body)`` for every sample on ``key``, on zenoh's thread (it must not
        block: hand over and return); returns what ends the subscription."""
        return self._shared.subscribe(key, callback)


class Device:
    """One device of one gateway."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared = shared
        self._found = found
        self.name, self.gateway, self.kind = found.name, found.gateway, found.kind
        self._latest: Latest | None = None

    def __repr__(self) -> str:
        return f"<Device {self.gateway}/{self.name} ({self.kind})>"

    def send(self, command: Any, *, timeout: float | None = None) -> dict[str, Any]:
        """Send a command (a dict, or a model of ``busgate.schemas``); the reply's body, or
        the error it carries raised as its class (``bc.error_for(code)``)."""
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.send(self._found, command, waited)
        return wait(sent, waited, f"{as_body(command).get('op')} on {self.gateway}/{self.name}")

    def move(self, position: int, **fields: Any) -> dict[str, Any]:
        """Move to ``position`` (the kind's units); ``fields`` add to the ``move`` op."""
        return self.send({"op": "move", "position": position, **fields})

    def velocity(self, rpm: float) -> dict[str, Any]:
        """Turn at ``rpm`` (a ZLAC706 in velocity mode)."""
        return self.send({"op": "velocity", "rpm": rpm})

    def enable(self) -> dict[str, Any]:
        """Let the device move again after an e-stop (its kind's re-enable command)."""
        return self.send(reenable_command(self.kind))

    def reset_estop(self) -> dict[str, Any]:
        """Out of the gateway's e-stop, back in the power state the device had before it and
        holding still: nothing moves until a new command (``{"op": "reset_estop"}``, as
        ``send`` sends it)."""
        return self.send({"op": "reset_estop"})

    def state(self, timeout: float = 2.0, *, max_age: float = 1.0) -> Any:
        """The device's latest telemetry, as its kind's model: one received in the last
        ``max_age`` seconds, else the next to come within ``timeout``."""
        if self._latest is None:
            self._latest = Latest(self._shared, self._found)
        payload = self._latest.wait(max_age, timeout)
        if payload is None:
            raise NoAnswerError(f"no state of {self.gateway}/{self.name} within {timeout:g} s")
        return self._shared.telemetry(self._found, payload)

    def states(self, timeout: float = 5.0) -> Iterator[Any]:
        """Each new state message of the device, as it comes, until ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        items: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        with Stream(self._shared, self._found, items.put):
            while (left := deadline - time.monotonic()) > 0:
                try:
                    payload = items.get(timeout=left)
                except queue.Empty:
                    return
                yield self._shared.telemetry(self._found, payload)

    def claim(self, ttl_s: float = 2.0) -> Claim:
        """Exclusive motion control while the ``with`` block runs: claimed on entry,
        renewed before ``ttl_s`` lapses, released on exit (``ClaimLostError`` on exit, and on
        any motion meanwhile, if it was lost)."""
        return Claim(self._shared, self._found, ttl_s)

    def follow(self) -> Follow:
        """A follow stream while the ``with`` block runs: ``set(position=…)`` (``rpm=…``
        for a ZLAC706); the latest target is sent at the device's period; the stream ends
        (``end_follow``) when the block exits."""
        return Follow(self._shared, self._found)


class Claim:
    """A claim held by a ``with`` block (``Device.claim``)."""

    def __init__(self, shared: Shared, found: Found, ttl_s: float) -> None:
        self._shared, self._found, self.ttl_s = shared, found, ttl_s
        self._lease: ClaimLease | None = None

    @property
    def lost(self) -> str | None:
        """Why the claim was lost, or ``None`` while it holds."""
        return None if self._lease is None else self._lease.lost

    def __enter__(self) -> Claim:
        lease = self._shared.claim(self._found, self.ttl_s)
        what = f"claim of {self._found.gateway}/{self._found.name}"
        try:
            wait(lease.take(), self._shared.core.timeout_s, what)
        except BaseException:
            self._shared.unclaim(lease)
            raise
        self._lease = lease
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        lease, self._lease = self._lease, None
        assert lease is not None
        _settle_on_exit(
            self._shared, self._shared.unclaim(lease), kind, f"release of {lease.device}"
        )


class Follow:
    """A follow stream held by a ``with`` block (``Device.follow``)."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self._sender: FollowSender | None = None

    def __enter__(self) -> Follow:
        self._sender = self._shared.follow(self._found)
        return self

    @property
    def sent(self) -> int:
        """How many targets were put so far (a target replaced while it waited is not)."""
        return 0 if self._sender is None else self._sender.puts

    def set(self, **target: Any) -> None:
        """The stream's new target (latest wins): ``position=…``, or ``rpm=…``; checked here
        (``OutOfRangeError``, ``BadCommandError``), put at most every 10 ms."""
        if self._sender is None:
            raise RuntimeError("set() outside the follow stream's with block")
        self._sender.set(target)

    def __exit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        sender, self._sender = self._sender, None
        assert sender is not None
        ended = self._shared.end_follow(self._found, sender)
        _settle_on_exit(self._shared, ended, kind, f"end of the stream of {self._found.name}")


def _settle_on_exit(
    shared: Shared, future: Future, kind: type[BaseException] | None, what: str
) -> None:
    """Wait for a block's last exchange; its failure is raised unless the block is already
    raising (that exception says more)."""
    try:
        wait(future, shared.core.timeout_s, what)
    except Exception:
        if kind is None:
            raise


class Trajectory(Handle):
    """A trajectory a gateway plays for this client (``Client.play``): its ``id``,
    ``gateway``, ``devices``, ``start_at`` and ``end_at`` (wall clock, as telemetry's ``ts``)."""

    def __enter__(self) -> Trajectory:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def wait(self, timeout: float | None = None) -> dict[str, Any]:
        """The result (``{"result": "succeeded" | "canceled" | "replaced" | "aborted",
        "reason"?, "errors"}``); by default waits until 30 s past ``end_at``."""
        waited = result_wait_s(self.end_at, timeout)
        return wait(self._watch.finished, waited, f"the result of trajectory {self.id}")

    def cancel(self, *, timeout: float | None = None) -> dict[str, Any]:
        """Each device decelerates to a stop and holds; the result is ``canceled``."""
        sent, waited = self._cancel(timeout)
        return wait(sent, waited, f"cancel of trajectory {self.id}")

    def feedback(self, timeout: float | None = None) -> Iterator[dict[str, Any]]:
        """Each feedback message as it comes (``t_s``, per device ``desired``,
        ``commanded``, ``measured``, ``error``), until the result or ``timeout``."""
        deadline = time.monotonic() + result_wait_s(self.end_at, timeout)
        items: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()
        remove = self._watch.add_sink(items.put)
        try:
            while self._watch.result is None and (left := deadline - time.monotonic()) > 0:
                try:
                    message = items.get(timeout=left)
                except queue.Empty:
                    return
                if "result" in message:
                    return
                yield message
        finally:
            remove()


class Bus:
    """One bus of one gateway: its group moves and scans."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self.name, self.gateway, self.protocol = found.name, found.gateway, found.kind

    def __repr__(self) -> str:
        return f"<Bus {self.gateway}/{self.name} ({self.protocol})>"

    def send(self, command: dict[str, Any], *, timeout: float | None = None) -> dict[str, Any]:
        """A bus command (``group_move``, ``scan``); the reply's body, or its error raised."""
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.bus_command(self._found, command, waited)
        return wait(sent, waited, f"{command.get('op')} on bus {self.gateway}/{self.name}")

    def group_move(
        self, targets: list[dict[str, Any]], *, timeout: float | None = None
    ) -> dict[str, Any]:
        """Start several devices of the bus together: ``[{"device": "la1", "position": 100},
        …]`` (``time_ms`` per target on a DS bus)."""
        return self.send({"op": "group_move", "targets": targets}, timeout=timeout)

    def scan(self, ids: list[int] | None = None, *, timeout: float | None = None) -> list[Any]:
        """Which ids answer on the bus (all of the protocol's when ``ids`` is None), and as
        what."""
        return self.send(scan_command(ids), timeout=timeout)["found"]
