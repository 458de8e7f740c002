"""The SDK's asyncio face: the same surface as ``busgate.client`` (``sync.py``), as
coroutines and async context managers.

zenoh-python has no asyncio API: its callbacks settle ``concurrent.futures.Future``s on
zenoh's threads, and ``asyncio.wrap_future`` hands each result to the loop with
``call_soon_threadsafe``; samples reach the loop the same way. Nothing here blocks the loop:
opening and closing the session, the only blocking zenoh calls, run in a worker thread.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Sequence
from concurrent.futures import Future
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
from busgate.client.sync import DEFAULT_TIMEOUT_S
from busgate.client.trajectories import Handle, one_gateway, play_body, result_wait_s
from busgate.schemas.api import InfoReply


async def wait(future: Future, timeout_s: float, what: str) -> Any:
    """Await the future's result, at most ``timeout_s`` plus zenoh's margin."""
    try:
        return await asyncio.wait_for(asyncio.wrap_future(future), timeout_s + WAIT_MARGIN_S)
    except TimeoutError:
        raise NoAnswerError(f"{what}: no answer within {timeout_s:g} s") from None


class connect:
    """``async with bc.aio.connect(endpoints, client_id=…) as c``, or ``c = await
    bc.aio.connect(…)`` and ``await c.close()``; the options are ``bc.connect``'s."""

    def __init__(
        self,
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
    ) -> None:
        self._options = dict(
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
        self._endpoints = endpoints
        self._client: Client | None = None

    async def _open(self) -> Client:
        core = await asyncio.to_thread(Core, self._endpoints, **self._options)  # type: ignore[arg-type]
        return Client(Shared(core))

    def __await__(self):  # type: ignore[no-untyped-def]
        return self._open().__await__()

    async def __aenter__(self) -> Client:
        self._client = await self._open()
        return self._client

    async def __aexit__(self, *exc_info: object) -> None:
        if self._client is not None:
            await self._client.close()


class Client:
    """One program's connection to a fleet of gateways, for asyncio."""

    def __init__(self, shared: Shared) -> None:
        self._shared = shared
        self.client_id = shared.core.client_id
        self.timeout = shared.core.timeout_s

    async def close(self) -> None:
        await asyncio.to_thread(self._shared.close)

    async def gateways(self, timeout: float = 1.0) -> dict[str, InfoReply]:
        """As ``busgate.client.Client.gateways``: ``InfoReply`` models, by name."""
        return await wait(self._shared.gateways(timeout), timeout, "info of the gateways")

    async def devices(self, timeout: float = 1.0) -> list[FleetDevice]:
        """As ``busgate.client.Client.devices``."""
        return await wait(self._shared.devices(timeout), timeout, "devices of the gateways")

    async def device(self, name: str, *, timeout: float | None = None) -> Device:
        waited = self.timeout if timeout is None else timeout
        found = await wait(self._shared.find(name, "device", waited), waited, f"finding {name}")
        return Device(self._shared, found)

    async def bus(self, name: str, *, timeout: float | None = None) -> Bus:
        waited = self.timeout if timeout is None else timeout
        found = await wait(self._shared.find(name, "bus", waited), waited, f"finding bus {name}")
        return Bus(self._shared, found)

    def on_gateways(self, callback: Callable[[str, bool], None]) -> Callable[[], None]:
        """As ``busgate.client.Client.on_gateways`` (the callback runs on zenoh's thread:
        ``loop.call_soon_threadsafe`` brings it to the loop)."""
        return self._shared.core.on_gateways(callback)

    async def estop(self, gateway: str | None = None) -> None:
        """As ``busgate.client.Client.estop``: the put goes before anything is awaited."""
        checked = self._shared.estop(gateway)
        await wait(checked, self.timeout, f"whether {gateway} is up (e-stop put)")

    async def reset_estop(self, gateway: str) -> None:
        """As ``busgate.client.Client.reset_estop``."""
        checked = self._shared.reset_estop(gateway)
        await wait(checked, self.timeout, f"whether {gateway} is up (reset put)")

    async def play(
        self,
        devices: list[str],
        points: list[dict[str, Any]],
        *,
        id: str | None = None,  # noqa: A002 - the contract's field name
        timeout: float | None = None,
        **options: Any,
    ) -> Trajectory:
        """As ``busgate.client.Client.play``."""
        waited = self.timeout if timeout is None else timeout
        finding = self._shared.find_all(devices, "device", waited)
        found = await wait(finding, waited, "finding devices")
        gateway = one_gateway(found)
        body = play_body(self.client_id, id, [f.name for f in found], points, options)
        started = trajectories.start(self._shared, gateway, body, waited)
        watch, accepted = await wait(started, waited, f"play of {body['id']} on {gateway}")
        return Trajectory(self._shared, watch, accepted)

    async def query(
        self, key: str, payload: Any = None, *, timeout: float | None = None
    ) -> Answers:
        waited = self.timeout if timeout is None else timeout
        return await wait(self._shared.query(key, payload, waited), waited, f"query on {key}")

    def put(self, key: str, payload: Any) -> None:
        self._shared.core.put(key, raw_payload(payload) or b"")

    def subscribe(self, key: str, callback: Callable[[str, Any], None]) -> Callable[[], None]:
        """As ``busgate.client.Client.subscribe``: ``callback`` runs on zenoh's thread; to
        reach the loop, hand over with ``loop.call_soon_threadsafe``."""
        return self._shared.subscribe(key, callback)


class Device:
    """One device of one gateway, for asyncio (``busgate.client.Device``'s methods)."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared = shared
        self._found = found
        self.name, self.gateway, self.kind = found.name, found.gateway, found.kind
        self._latest: Latest | None = None

    def __repr__(self) -> str:
        return f"<aio.Device {self.gateway}/{self.name} ({self.kind})>"

    async def send(self, command: Any, *, timeout: float | None = None) -> dict[str, Any]:
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.send(self._found, command, waited)
        what = f"{as_body(command).get('op')} on {self.gateway}/{self.name}"
        return await wait(sent, waited, what)

    async def move(self, position: int, **fields: Any) -> dict[str, Any]:
        return await self.send({"op": "move", "position": position, **fields})

    async def velocity(self, rpm: float) -> dict[str, Any]:
        return await self.send({"op": "velocity", "rpm": rpm})

    async def enable(self) -> dict[str, Any]:
        return await self.send(reenable_command(self.kind))

    async def reset_estop(self) -> dict[str, Any]:
        return await self.send({"op": "reset_estop"})

    async def state(self, timeout: float = 2.0, *, max_age: float = 1.0) -> Any:
        if self._latest is None:
            self._latest = Latest(self._shared, self._found)
        payload = self._latest.recent(max_age)
        if payload is None:
            loop = asyncio.get_running_loop()
            came: asyncio.Future[bytes] = loop.create_future()
            withdraw = self._latest.on_next(lambda p: loop.call_soon_threadsafe(_settle, came, p))
            try:
                payload = await asyncio.wait_for(came, timeout)
            except TimeoutError:
                withdraw()
                raise NoAnswerError(
                    f"no state of {self.gateway}/{self.name} within {timeout:g} s"
                ) from None
        return self._shared.telemetry(self._found, payload)

    async def states(self, timeout: float = 5.0) -> AsyncIterator[Any]:
        loop = asyncio.get_running_loop()
        items: asyncio.Queue[bytes] = asyncio.Queue()
        deadline = time.monotonic() + timeout
        with Stream(
            self._shared, self._found, lambda p: loop.call_soon_threadsafe(items.put_nowait, p)
        ):
            while (left := deadline - time.monotonic()) > 0:
                try:
                    payload = await asyncio.wait_for(items.get(), left)
                except TimeoutError:
                    return
                yield self._shared.telemetry(self._found, payload)

    def claim(self, ttl_s: float = 2.0) -> Claim:
        return Claim(self._shared, self._found, ttl_s)

    def follow(self) -> Follow:
        return Follow(self._shared, self._found)


def _settle(future: asyncio.Future, value: Any) -> None:
    if not future.done():
        future.set_result(value)


class Claim:
    """``async with device.claim(ttl_s)``: as ``busgate.client.Claim``."""

    def __init__(self, shared: Shared, found: Found, ttl_s: float) -> None:
        self._shared, self._found, self.ttl_s = shared, found, ttl_s
        self._lease: ClaimLease | None = None

    @property
    def lost(self) -> str | None:
        return None if self._lease is None else self._lease.lost

    async def __aenter__(self) -> Claim:
        lease = self._shared.claim(self._found, self.ttl_s)
        what = f"claim of {self._found.gateway}/{self._found.name}"
        try:
            await wait(lease.take(), self._shared.core.timeout_s, what)
        except BaseException:
            self._shared.unclaim(lease)
            raise
        self._lease = lease
        return self

    async def __aexit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        lease, self._lease = self._lease, None
        assert lease is not None
        released = self._shared.unclaim(lease)
        await _settle_on_exit(self._shared, released, kind, f"release of {lease.device}")


class Follow:
    """``async with device.follow() as f``: ``f.set(…)`` does not wait (a put)."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self._sender: FollowSender | None = None

    async def __aenter__(self) -> Follow:
        self._sender = self._shared.follow(self._found)
        return self

    @property
    def sent(self) -> int:
        """How many targets were put so far (a target replaced while it waited is not)."""
        return 0 if self._sender is None else self._sender.puts

    def set(self, **target: Any) -> None:
        if self._sender is None:
            raise RuntimeError("set() outside the follow stream's async with block")
        self._sender.set(target)

    async def __aexit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        sender, self._sender = self._sender, None
        assert sender is not None
        ended = self._shared.end_follow(self._found, sender)
        await _settle_on_exit(self._shared, ended, kind, f"end of the stream of {self._found.name}")


async def _settle_on_exit(
    shared: Shared, future: Future, kind: type[BaseException] | None, what: str
) -> None:
    try:
        await wait(future, shared.core.timeout_s, what)
    except Exception:
        if kind is None:
            raise


class Trajectory(Handle):
    """A trajectory a gateway plays (``await c.play(...)``), for asyncio: as
    ``busgate.client.Trajectory``."""

    async def __aenter__(self) -> Trajectory:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        self.close()

    async def wait(self, timeout: float | None = None) -> dict[str, Any]:
        waited = result_wait_s(self.end_at, timeout)
        return await wait(self._watch.finished, waited, f"the result of trajectory {self.id}")

    async def cancel(self, *, timeout: float | None = None) -> dict[str, Any]:
        sent, waited = self._cancel(timeout)
        return await wait(sent, waited, f"cancel of trajectory {self.id}")

    async def feedback(self, timeout: float | None = None) -> AsyncIterator[dict[str, Any]]:
        loop = asyncio.get_running_loop()
        items: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

        def sink(message: dict[str, Any]) -> None:
            loop.call_soon_threadsafe(items.put_nowait, message)

        deadline = time.monotonic() + result_wait_s(self.end_at, timeout)
        remove = self._watch.add_sink(sink)
        try:
            while self._watch.result is None and (left := deadline - time.monotonic()) > 0:
                try:
                    message = await asyncio.wait_for(items.get(), left)
                except TimeoutError:
                    return
                if "result" in message:
                    return
                yield message
        finally:
            remove()


class Bus:
    """One bus of one gateway, for asyncio."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self._shared, self._found = shared, found
        self.name, self.gateway, self.protocol = found.name, found.gateway, found.kind

    def __repr__(self) -> str:
        return f"<aio.Bus {self.gateway}/{self.name} ({self.protocol})>"

    async def send(self, command: dict[str, Any], *, timeout: float | None = None) -> Any:
        waited = self._shared.core.timeout_s if timeout is None else timeout
        sent = self._shared.bus_command(self._found, command, waited)
        return await wait(sent, waited, f"{command.get('op')} on bus {self.gateway}/{self.name}")

    async def group_move(
        self, targets: list[dict[str, Any]], *, timeout: float | None = None
    ) -> Any:
        return await self.send({"op": "group_move", "targets": targets}, timeout=timeout)

    async def scan(self, ids: list[int] | None = None, *, timeout: float | None = None) -> Any:
        return (await self.send(scan_command(ids), timeout=timeout))["found"]
