"""The SDK's asyncio face (``busgate.client.aio``) against a real ``busgate demo`` child process:
the same surface as the blocking face (tests/test_client_sdk.py), as coroutines, async
iterators and async context managers. Each test runs its coroutine with ``asyncio.run`` (no
pytest-asyncio), under a hang guard.

One demo for the module; it is the only gateway, so bare names resolve to it. A test that
e-stops enables every device again.
"""

from __future__ import annotations

import asyncio
import inspect
import os
import signal
import time
from collections.abc import Awaitable, Callable

import pytest

import busgate.client as bc
from busgate.schemas.api import TELEMETRY_MODELS, InfoReply
from busgate.schemas.inspire_la import Move
from tests.sdk_helpers import (
    DEMO_DEVICES,
    STALE_S,
    EventWatch,
    fresh_positions,
    patiently_async,
    the_client_id,
)

POSITIONS = fresh_positions(104)
#: Hang guards, not speed requirements.
DEADLINE_S = 10.0
TEST_DEADLINE_S = 60.0


@pytest.fixture(scope="module")
def demo(module_demo):
    return module_demo


@pytest.fixture
def connect(demo, request) -> Callable[..., bc.aio.connect]:
    """``connect(suffix)``: ``bc.aio.connect`` to the demo as a client named after the test."""

    def aio_connect(suffix: str = "", **options) -> bc.aio.connect:
        name = f"{request.node.name}-{suffix}" if suffix else request.node.name
        return bc.aio.connect(demo.endpoint, client_id=the_client_id(name), **options)

    return aio_connect


def run(coroutine: Awaitable[object]) -> object:
    return asyncio.run(asyncio.wait_for(coroutine, TEST_DEADLINE_S))


async def until(condition: Callable[[], object], timeout: float = DEADLINE_S) -> None:
    """Until ``condition()`` (awaited when it is a coroutine) is true; fail after ``timeout``
    seconds."""
    deadline = time.monotonic() + timeout
    while not await _value(condition()):
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


async def _value(result: object) -> object:
    return await result if inspect.isawaitable(result) else result


async def settled(device, **expected) -> None:
    async def shows() -> bool:
        state = await device.state()
        return all(getattr(state, key) == value for key, value in expected.items())

    await until(shows)


async def enable_every_device(client) -> None:
    for name in DEMO_DEVICES:
        await patiently_async((await client.device(name)).enable)


# -- connecting, finding ---------------------------------------------------------------------


def test_connect_as_an_async_context_manager_or_awaited(connect) -> None:
    async def main() -> None:
        async with connect("with") as client:
            assert isinstance(client, bc.aio.Client)
            infos = await client.gateways(timeout=1.0)
            assert set(infos) == {"demo"}
            for name, kind in DEMO_DEVICES.items():
                device = await client.device(name)  # bare: the demo is the only gateway
                assert (device.name, device.gateway, device.kind) == (name, "demo", kind)
            named = await client.device("demo/la1")
            assert (named.name, named.gateway) == ("la1", "demo")
        client = await connect("awaited")
        try:
            assert (await client.device("servo1")).kind == "ds_servo"
        finally:
            await client.close()

    run(main())


def test_gateways_are_info_models_read_by_key_too_and_devices_list_each_in_order(
        connect) -> None:
    async def main() -> None:
        async with connect() as client:
            infos = await client.gateways(timeout=1.0)
            devices = await client.devices(timeout=1.0)
        [info] = infos.values()
        assert type(info) is InfoReply and info.gateway == "demo"
        listed = {d.name: (bus.name, d.kind, d.id) for bus in info.buses for d in bus.devices}
        assert listed == {d["name"]: (bus["name"], d["kind"], d["id"])
                          for bus in info["buses"] for d in bus["devices"]}
        assert [(d.gateway, d.name) for d in devices] == [("demo", n) for n in sorted(listed)]
        assert all(type(d) is bc.FleetDevice for d in devices)
        assert {d.name: (d.bus, d.kind, d.id) for d in devices} == listed
        assert {d.name: d.kind for d in devices} == DEMO_DEVICES
        for device in devices:
            assert device.state is None or type(device.state) is TELEMETRY_MODELS[device.kind]

    run(main())


def test_unknown_names_and_silent_gateways_raise_their_errors(connect) -> None:
    async def main() -> None:
        async with connect() as client:
            with pytest.raises(bc.error_for("unknown_device")):
                await client.device("la9")
            with pytest.raises(bc.error_for("unknown_bus")):
                await client.bus("demo/uart9")
            with pytest.raises(bc.UnknownGatewayError):  # the demo answers, not gw9
                await client.device("gw9/la1", timeout=0.5)

    run(main())


# -- telemetry -------------------------------------------------------------------------------


def test_state_is_the_kinds_model_for_every_device_at_once(connect) -> None:
    async def main() -> None:
        async with connect() as client:
            devices = [await client.device(name) for name in DEMO_DEVICES]
            states = await asyncio.gather(*(device.state(timeout=2.0) for device in devices))
            for device, state in zip(devices, states, strict=True):
                assert type(state) is TELEMETRY_MODELS[device.kind]
                assert (state.device, state.kind) == (device.name, device.kind)

    run(main())


def test_states_yields_each_new_sample_until_the_timeout(connect) -> None:
    async def main() -> None:
        async with connect() as client:
            la2 = await client.device("la2")
            await patiently_async(la2.enable)
            target = next(POSITIONS)
            samples = []
            started = time.monotonic()
            async for state in la2.states(timeout=1.5):
                if not samples:
                    await patiently_async(la2.move, target)
                samples.append(state)
            elapsed = time.monotonic() - started
            assert all(type(s) is TELEMETRY_MODELS["inspire_la"] for s in samples)
            assert any(s.target == target for s in samples), "no sample came after the move"
            stamps = [s.ts for s in samples]
            assert stamps == sorted(stamps) and len(set(stamps)) >= 5, stamps
            assert 1.5 <= elapsed < 1.5 + 2.0, "the iteration did not end at its timeout"

    run(main())


# -- commands ---------------------------------------------------------------------------------


def test_send_move_enable_and_velocity(connect) -> None:
    async def main() -> None:
        async with connect() as client:
            la3 = await client.device("la3")
            assert (await patiently_async(la3.enable))["state"]["power"] == "on"
            first, second, third = next(POSITIONS), next(POSITIONS), next(POSITIONS)
            reply = await patiently_async(la3.send, {"op": "move", "position": first})
            assert reply["ok"] is True and reply["state"]["target"] == first
            reply = await patiently_async(la3.send, Move(op="move", position=second))
            assert reply["state"]["target"] == second
            assert (await patiently_async(la3.move, third))["state"]["target"] == third
            await settled(la3, position=third, target=third)
            wheel = await client.device("wheel")
            await patiently_async(wheel.send, {"op": "set_mode", "mode": "velocity"})
            await patiently_async(wheel.enable)
            try:
                reply = await patiently_async(wheel.velocity, -80)
                assert reply["state"]["target_speed_rpm"] == pytest.approx(-80, abs=0.5)
            finally:
                await patiently_async(wheel.velocity, 0)

    run(main())


@pytest.mark.parametrize(("command", "code"), [
    ({"op": "spin"}, "bad_command"),
    ({"op": "move", "position": 2001}, "out_of_range"),
    ({"op": "move", "position": 1, "pad": "x" * 70_000}, "too_large"),
], ids=["bad_command", "out_of_range", "too_large"])
def test_the_gateways_refusal_is_raised_as_its_codes_class(connect, command, code) -> None:
    async def main() -> None:
        async with connect() as client:
            la2 = await client.device("la2")
            with pytest.raises(bc.error_for(code)) as refused:
                await la2.send(command)
            assert refused.value.code == code and refused.value.gateway == "demo"

    run(main())


# -- claims and follow streams ---------------------------------------------------------------


def test_a_claim_holds_past_its_ttl_refusing_others_and_is_released_on_exit(connect) -> None:
    async def main() -> None:
        async with connect("holder") as holder, connect("other") as other:
            mine, theirs = await holder.device("la2"), await other.device("la2")
            await patiently_async(mine.enable)
            refusals = []
            async with mine.claim(ttl_s=1.0) as claim:
                started = time.monotonic()
                while (held := time.monotonic() - started) < 1.6:
                    with pytest.raises(bc.ClaimedError) as refused:
                        await theirs.move(next(POSITIONS))
                    assert refused.value.holder == holder.client_id
                    assert (await patiently_async(mine.move, next(POSITIONS)))["ok"] is True
                    refusals.append(held)
                    await asyncio.sleep(0.05)
                assert claim.lost is None
            assert max(refusals) > 1.2, refusals
            assert (await patiently_async(theirs.move, next(POSITIONS)))["ok"] is True
            with pytest.raises(ZeroDivisionError):
                async with mine.claim(ttl_s=2.0):
                    1 / 0  # noqa: B018 - the block fails
            moved = await patiently_async(theirs.move, next(POSITIONS))
            assert moved["ok"] is True, "not released"

    run(main())


def test_a_follow_stream_ends_with_end_follow_when_its_block_raises(demo, connect) -> None:
    async def main() -> None:
        async with connect() as client:
            la1 = await client.device("la1")
            await patiently_async(la1.enable)
            with EventWatch(demo.endpoint) as watch:
                started = time.monotonic()
                async with la1.claim(ttl_s=2.0):
                    await until(lambda: watch.of("la1", "claimed", since=started))
                    with pytest.raises(ZeroDivisionError):
                        async with la1.follow() as stream:
                            stream.set(position=300)
                            stream.set(position=400)  # latest wins
                            for _ in range(3):  # a few ticks (20 ms), inside the stale timeout
                                await asyncio.sleep(STALE_S / 4)
                                stream.set(position=400)
                            1 / 0  # noqa: B018 - the block fails
                await asyncio.sleep(STALE_S + 1.5)
                ends = watch.of("la1", "stream_stopped", "stream_stale", since=started)
            assert [(e["type"], e.get("reason")) for e in ends] == [
                ("stream_stopped", f"ended by {client.client_id}")]
            await settled(la1, target=400, position=400)
            with pytest.raises(bc.CommandError, match=r"set\(\) outside"):  # a BusgateError
                stream.set(position=500)

    run(main())


# -- buses and e-stops -----------------------------------------------------------------------


def test_bus_group_move_and_scan(connect) -> None:
    async def main() -> None:
        async with connect() as client:
            uart0 = await client.bus("uart0")
            assert (uart0.name, uart0.gateway, uart0.protocol) == ("uart0", "demo", "inspire_la")
            la2, la3 = await client.device("la2"), await client.device("la3")
            await patiently_async(la2.enable)
            await patiently_async(la3.enable)
            first, second = next(POSITIONS), next(POSITIONS)
            targets = [{"device": "la2", "position": first}, {"device": "la3", "position": second}]
            reply = await patiently_async(uart0.group_move, targets)
            assert reply["ok"] is True
            await settled(la2, position=first)
            await settled(la3, position=second)
            found = await patiently_async(uart0.scan, [1, 3, 7])
            assert sorted(f["id"] for f in found) == [1, 3]
            with pytest.raises(bc.error_for("unknown_device")):
                await uart0.group_move([{"device": "wheel", "position": 1}])

    run(main())


@pytest.mark.parametrize("gateway", ["demo", None], ids=["one gateway", "the fleet"])
def test_an_estop_stops_the_devices_until_enable(connect, gateway) -> None:
    async def main() -> None:
        async with connect() as client:
            la1, servo1 = await client.device("la1"), await client.device("servo1")
            await patiently_async(la1.enable)
            await patiently_async(servo1.enable)
            try:
                await client.estop(gateway)

                async def both_estopped() -> bool:
                    return (await la1.state()).estopped and (await servo1.state()).estopped

                await until(both_estopped)
                for device in (la1, servo1):
                    with pytest.raises(bc.error_for("estopped")):
                        await device.move(next(POSITIONS))
                for device in (la1, servo1):
                    await patiently_async(device.enable)
                    assert (await patiently_async(device.move, next(POSITIONS)))["ok"] is True
            finally:
                await enable_every_device(client)

    run(main())


def test_a_state_timed_out_in_a_closed_loop_does_not_starve_the_next_wait(demo, connect) -> None:
    """The demo is frozen (SIGSTOP) so the first wait times out for sure, then thawed while
    the second waits: the next sample must reach the second."""
    async def open_device():
        client = await connect()
        return client, await client.device("la1")

    client, la1 = asyncio.run(open_device())
    try:
        asyncio.run(la1.state())  # subscribed, and that wait is over
        os.kill(demo.process.pid, signal.SIGSTOP)
        try:
            with pytest.raises(bc.NoAnswerError):
                asyncio.run(la1.state(timeout=0.3, max_age=0.0))  # its loop closes with it

            async def second_wait() -> object:
                waiting = asyncio.create_task(la1.state(timeout=2.0, max_age=0.0))
                await asyncio.sleep(0.1)  # registered
                os.kill(demo.process.pid, signal.SIGCONT)
                return await waiting

            state = asyncio.run(second_wait())
        finally:
            os.kill(demo.process.pid, signal.SIGCONT)
        assert state.device == "la1"
    finally:
        asyncio.run(client.close())
