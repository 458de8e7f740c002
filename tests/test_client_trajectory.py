"""Trajectories through the SDK (``Client.play`` and ``bc.aio``) against a real ``busgate
demo``: accepted with its times, feedback as it plays, one result, cancel, replace, refusals
as the error classes of their codes. (The wire's side of it: tests/test_trajectory_wire.py.)"""

from __future__ import annotations

import asyncio
import itertools
import time

import pytest

import busgate.client as bc
from busgate.errors import CommandError
from tests.sdk_helpers import patiently, patiently_async

TIMEOUT_S = 10.0  # a hang guard, not a speed requirement
#: Plays of a test that expects one to succeed, at most: under load a simulated device may
#: miss three polls and go offline a moment, which rightly aborts the trajectory moving it.
TRIES = 3


def offline_abort(result: dict) -> bool:
    return result["result"] == "aborted" and "offline" in result.get("reason", "")


@pytest.fixture(scope="module")
def client(module_demo):
    with bc.connect(module_demo.endpoint, client_id="trajectory-test", timeout=TIMEOUT_S) as c:
        yield c


def test_a_play_is_accepted_feeds_back_and_ends_with_one_result(client) -> None:
    points = [{"t_s": 0.3, "positions": [1400, 900]}, {"t_s": 0.6, "positions": [800, 600]}]
    for _ in range(TRIES):
        before = time.time()
        with patiently(lambda: client.play(["la1", "demo/la2"], points, goal_tolerance=[40, 40],
                                           goal_time_s=2.0)) as t:
            assert (t.gateway, t.devices) == ("demo", ["la1", "la2"])
            assert before < t.start_at < t.end_at and t.end_at - t.start_at == pytest.approx(0.6)
            feedback = list(t.feedback(timeout=TIMEOUT_S))
            result = t.wait(timeout=TIMEOUT_S)
        if not offline_abort(result):
            break
    assert result["result"] == "succeeded" and result["id"] == t.id
    assert t.result == result
    assert len(feedback) >= 5  # ten a second over at least 0.6 s
    assert {d["device"] for d in feedback[-1]["devices"]} == {"la1", "la2"}
    assert all(m["t_s"] <= n["t_s"] for m, n in itertools.pairwise(feedback))


def test_a_new_play_replaces_the_old_and_cancel_ends_it_canceled(client) -> None:
    long = [{"t_s": 5.0, "positions": [1900]}]
    for _ in range(TRIES):  # (a device offline a moment, under load, aborts the second)
        first = patiently(lambda: client.play(["la3"], long))
        second = patiently(lambda: client.play(["la3", "servo1"],
                                               [{"t_s": 5.0, "positions": [1900, 3000]}]))
        assert first.wait(timeout=TIMEOUT_S)["result"] == "replaced"
        [status] = client.query("busgate/demo/trajectory", {"op": "status"})
        time.sleep(0.2)
        if [r["id"] for r in status.body["trajectories"]] == [second.id] and second.result is None:
            break
        second.wait(timeout=TIMEOUT_S)
    assert [r["id"] for r in status.body["trajectories"]] == [second.id]
    assert second.cancel()["canceled"] == second.id
    assert second.wait(timeout=TIMEOUT_S)["result"] == "canceled"
    with pytest.raises(bc.BadCommandError, match="no trajectory"):
        second.cancel()


class Interrupted(Exception):
    """What ends a play's block here: a Ctrl-C, or the program's own error."""


def _played_out(client: bc.Client, trajectory_id: str) -> None:
    """Until the gateway plays ``trajectory_id`` no longer (a hang guard's time at most)."""
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        [status] = client.query("busgate/demo/trajectory", {"op": "status"})
        if trajectory_id not in [r["id"] for r in status.body["trajectories"]]:
            return
        assert time.monotonic() < deadline, "the trajectory plays on"
        time.sleep(0.05)


TWENTY_SECONDS = [{"t_s": 20.0, "positions": [1900]}]


def test_a_play_block_an_exception_ends_cancels_the_trajectory(client) -> None:
    """It played on for as long as the client stayed open (a notebook, a program that goes on
    after its ``except``), its block's exit only closing the watch."""
    with pytest.raises(Interrupted), patiently(lambda: client.play(["la3"], TWENTY_SECONDS)) as t:
        raise Interrupted
    _played_out(client, t.id)  # the client open all along


def test_so_does_an_asyncio_play_block(client, module_demo) -> None:
    async def left_by_an_exception() -> None:
        async with bc.aio.connect(module_demo.endpoint, client_id="trajectory-aio-left") as c:
            with pytest.raises(Interrupted):
                async with await patiently_async(lambda: c.play(["la3"], TWENTY_SECONDS)) as t:
                    raise Interrupted
            await asyncio.to_thread(_played_out, client, t.id)  # while this client is open

    asyncio.run(left_by_an_exception())


def test_refusals_are_the_classes_of_their_codes_and_nothing_runs(client) -> None:
    with pytest.raises(bc.OutOfRangeError, match=r"joint la1: position .* beyond its max "):
        patiently(lambda: client.play(["la1"], [{"t_s": 0.2, "positions": [2500]}]))
    with pytest.raises(bc.BadCommandError, match="after"):
        client.play(["la1"], [{"t_s": 0.4, "positions": [1]}, {"t_s": 0.2, "positions": [2]}])
    with pytest.raises(bc.OutOfRangeError, match="start_at"):
        client.play(["la1"], [{"t_s": 0.2, "positions": [10]}], start_at=time.time() - 1)
    with pytest.raises(bc.UnknownDeviceError):
        client.play(["la9"], [{"t_s": 0.2, "positions": [10]}])
    with pytest.raises(bc.BadCommandError, match="needs position mode"):
        client.play(["wheel"], [{"t_s": 0.2, "positions": [10]}])
    [status] = client.query("busgate/demo/trajectory", {"op": "status"})
    assert status.body["trajectories"] == []


def test_a_trajectory_plays_the_devices_of_one_gateway() -> None:
    from busgate.client.base import Found
    from busgate.client.trajectories import one_gateway

    assert one_gateway([Found("gw1", "la1", "inspire_la")] * 2) == "gw1"
    with pytest.raises(CommandError, match="one gateway"):
        one_gateway([Found("gw1", "la1", "inspire_la"), Found("gw2", "la1", "inspire_la")])


def test_the_asyncio_face_plays_too(module_demo) -> None:
    async def main() -> tuple[list, dict]:
        async with bc.aio.connect(module_demo.endpoint, client_id="trajectory-aio") as c:
            for _ in range(TRIES):
                t = await patiently_async(c.play, ["la2"], [{"t_s": 0.3, "positions": [1234]}])
                feedback = [message async for message in t.feedback(timeout=TIMEOUT_S)]
                result = await t.wait(timeout=TIMEOUT_S)
                if not offline_abort(result):
                    break
            return feedback, result

    feedback, result = asyncio.run(main())
    assert result["result"] == "succeeded" and len(feedback) >= 2
