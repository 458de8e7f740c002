"""The trajectory key's lanes (gateway/trajectory/lanes.py), with real threads and a command
that holds its lane until the test lets it go: a cancel or a status never waits behind plays;
plays wait at most ``MAX_WAITING_PLAYS`` deep and are answered ``busy`` past that or past
their start deadline, never carried out; what cannot be read on arrival is a play's."""

from __future__ import annotations

import json
import threading

import pytest

from busgate.gateway.trajectory import lanes as trajectory_lanes
from busgate.gateway.trajectory.lanes import MAX_WAITING_PLAYS, Lane, TrajectoryLanes

TIMEOUT_S = 5.0


class Held:
    """A trajectory command whose plays each wait for ``release`` before they answer."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()  # a play is on the lane's thread
        self.carried_out: list[dict] = []

    def __call__(self, payload: bytes, came_under: int | None = None) -> dict:
        fields = json.loads(payload)
        if fields.get("op") == "play":
            self.started.set()
            assert self.release.wait(TIMEOUT_S)
        elif fields.get("op") == "explode":
            raise RuntimeError("a bug")
        self.carried_out.append(fields)
        return {"ok": True, "op": fields.get("op")}


def play(number: int) -> bytes:
    return json.dumps({"op": "play", "id": f"p{number}"}).encode()


@pytest.fixture
def held():
    command = Held()
    lanes = TrajectoryLanes(command)
    yield command, lanes
    command.release.set()
    lanes.close()


def test_cancel_and_status_are_answered_while_a_play_holds_its_lane(held):
    command, lanes = held
    playing = lanes.submit(play(1))
    cancel = lanes.submit(b'{"op": "cancel", "id": "p1"}')
    status = lanes.submit(b'{"op": "status"}')
    assert cancel.result(TIMEOUT_S)["op"] == "cancel"
    assert status.result(TIMEOUT_S)["op"] == "status"
    assert not playing.done()
    command.release.set()
    assert playing.result(TIMEOUT_S)["ok"]


def test_plays_past_the_bound_are_busy_at_once_and_never_carried_out(held):
    command, lanes = held
    first = lanes.submit(play(0))
    assert command.started.wait(TIMEOUT_S)  # on the lane's thread: no longer waiting
    waiting = [lanes.submit(play(n)) for n in range(1, MAX_WAITING_PLAYS + 1)]
    over = lanes.submit(play(99))
    assert over.done() and over.result()["error"]["code"] == "busy"
    assert not any(f.done() for f in waiting)
    command.release.set()
    assert all(f.result(TIMEOUT_S)["ok"] for f in [first, *waiting])
    assert [c["id"] for c in command.carried_out] == [f"p{n}" for n in range(len(waiting) + 1)]


def test_a_play_not_started_within_its_deadline_is_busy_and_never_carried_out(monkeypatch):
    monkeypatch.setattr(trajectory_lanes, "PLAY_START_S", 0.05)
    command = Held()
    lanes = TrajectoryLanes(command)
    try:
        first = lanes.submit(play(1))
        late = lanes.submit(play(2))
        threading.Timer(0.2, command.release.set).start()  # the first holds past the deadline
        assert first.result(TIMEOUT_S)["ok"]
        reply = late.result(TIMEOUT_S)
        assert reply["error"]["code"] == "busy" and "not carried out" in reply["error"]["message"]
        assert [c["id"] for c in command.carried_out] == ["p1"]
    finally:
        command.release.set()
        lanes.close()


def test_a_flood_of_control_commands_is_bounded_too():
    gate = threading.Event()
    lane = Lane("trajectory command", 2, None)
    try:
        running = threading.Event()

        def blocking() -> dict:
            running.set()
            return {"ok": gate.wait(TIMEOUT_S)}

        blocked = lane.submit(blocking)
        assert running.wait(TIMEOUT_S)
        queued = [lane.submit(lambda: {"ok": True}) for _ in range(3)]
        assert [f.done() for f in queued] == [False, False, True]
        assert queued[2].result()["error"]["code"] == "busy"
        gate.set()
        assert blocked.result(TIMEOUT_S)["ok"]
    finally:
        gate.set()
        lane.close()


@pytest.mark.parametrize("payload", [
    b"not json", b'{"op": ["cancel"]}', json.dumps({"op": "status", "pad": "x" * 5000}).encode(),
])
def test_what_cannot_be_read_on_arrival_goes_to_the_play_lane(held, payload):
    """Malformed, an op that is no name, or too large to read on arrival: behind the play."""
    command, lanes = held
    lanes.submit(play(1))
    answer = lanes.submit(payload)
    assert not answer.done()
    command.release.set()
    assert answer.result(TIMEOUT_S)  # answered (a refusal for the malformed one)


def test_a_bug_is_answered_internal_not_raised(held):
    _, lanes = held
    reply = lanes.submit(b'{"op": "explode"}').result(TIMEOUT_S)
    assert reply["error"]["code"] == "internal"
