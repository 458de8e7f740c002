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
