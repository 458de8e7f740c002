"""Telemetry that tells the truth (gateway/scheduler/telemetry.py, rules 1 and 2): a state's
``ts`` is when its values were read from the device, not when it was published, and a device
with news is published only when its state changed in more than its age. First with a real
driver on a fake clock, then end to end: a follow stream to an Inspire LA (its follow frame
has no reply) publishes a state per reading, not one per tick."""

from __future__ import annotations

import itertools
import json
import time

import zenoh

from busgate.codecs import inspire_la as la
from busgate.gateway.drivers.inspire_la import InspireLaDriver, PowerStage
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.telemetry import STALE_PERIODS, Telemetry
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.zenoh_session import session_config
from tests.test_telemetry import telemetry_of
from tests.test_zenoh_api import Daemon, config_for, connected

POLL_S = 0.1
#: Wall time and the bus clock are read a moment apart: this much either way.
CONVERSION_S = 0.005


def read_la() -> tuple[InspireLaDriver, BusDevices, Telemetry, list]:
    """An actuator polled every ``POLL_S`` that has published its first state: read at 10.0
    (fake bus clock), published at 10.01."""
    la1 = InspireLaDriver("la1", 1)
    devices = BusDevices([la1])
    telemetry, _, states = telemetry_of(devices, {"la1": POLL_S})
    la1.heard(10.0)
    telemetry.publish(10.01)
    return la1, devices, telemetry, states


def same_but_age(a: dict, b: dict) -> bool:
    return {**a, "last_reply_age_s": None} == {**b, "last_reply_age_s": None}


def test_ts_is_when_the_values_were_read_in_wall_time_not_when_published():
    la1, _, telemetry, states = read_la()
    [(_, published)] = states
    assert abs(published["ts"] - (time.time() - 0.01)) < CONVERSION_S
    later = telemetry.reply_state(la1, 10.25)  # a command's reply, with no reading of its own
    assert later["ts"] == published["ts"], "one reading, one ts, whenever it is stamped"
    assert later["last_reply_age_s"] == 0.25


def test_news_that_changed_nothing_publishes_nothing():
    la1, devices, telemetry, states = read_la()
    for moment in (10.03, 10.05, 10.07):  # follow ticks: no reply, the state is as it was
        devices.touched(la1)
        telemetry.publish(moment)
    assert len(states) == 1
    assert telemetry.states["la1"] is states[0][1], "the last state published is kept"


def test_news_that_changed_a_value_without_a_reading_publishes_it_with_the_same_ts():
    la1, devices, telemetry, states = read_la()
    la1.power = PowerStage.PAUSED  # a pause's frame has no reply: nothing was read
    devices.touched(la1)
    telemetry.publish(10.03)
    la1.power = PowerStage.ESTOPPED  # an e-stop, flag and power
    devices.touched(la1)
    telemetry.publish(10.05)
    assert [(s["power"], s["enabled"], s["estopped"]) for _, s in states] == [
        ("on", True, False), ("paused", False, False), ("estopped", False, True)]
    assert len({s["ts"] for _, s in states}) == 1, "one reading"


def test_a_replys_state_is_published_before_the_reply_when_it_is_news_and_only_then():
    la1, devices, telemetry, states = read_la()
    la1.power = PowerStage.PAUSED  # a command's effect, its reply built before the next publish
    devices.touched(la1)
    replied = telemetry.reply_state(la1, 10.02)
    assert states[-1] == ("la1", replied) and telemetry.states["la1"] is replied, (
        "the info and the stream show what the reply says before the client holds it")
    telemetry.publish(10.03)
    again = telemetry.reply_state(la1, 10.04)  # a read-only command: nothing new
    assert len(states) == 2 and telemetry.states["la1"] is replied
    assert same_but_age(again, replied) and again["last_reply_age_s"] > replied["last_reply_age_s"]


def test_a_device_never_read_is_published_again_only_when_its_state_changes():
    la1 = InspireLaDriver("la1", 1)  # streamed, never polled: nothing is ever read
    devices = BusDevices([la1])
    telemetry, _, states = telemetry_of(devices, {})
    telemetry.publish(1.0)
    for moment in (1.01, 1.02):  # its follow ticks
        devices.touched(la1)
        telemetry.publish(moment)
    assert len(states) == 1, "a state stamped when taken is not a new reading"
    la1.power = PowerStage.ESTOPPED
    devices.touched(la1)
    telemetry.publish(1.03)
    assert [s["estopped"] for _, s in states] == [False, True]


def test_a_new_reply_publishes_with_a_new_ts():
    la1, devices, telemetry, states = read_la()
    la1.heard(10.1)  # the next poll's reply, values unchanged
    devices.touched(la1)
    telemetry.publish(10.11)
    assert len(states) == 2
    (_, first), (_, second) = states
    assert second["ts"] > first["ts"]
    assert abs(second["ts"] - (time.time() - 0.01)) < CONVERSION_S, "read 0.01 s before"
    assert not same_but_age(first, second)


def test_going_stale_publishes_with_the_ts_of_the_last_reading():
    la1, devices, telemetry, states = read_la()
    devices.touched(la1)  # an unanswered poll
    telemetry.publish(10.0 + STALE_PERIODS * POLL_S + 0.01)
    assert [state["stale"] for _, state in states] == [False, True]
    assert states[1][1]["ts"] == states[0][1]["ts"], "nothing was read since"


def test_a_follow_stream_publishes_a_state_per_reading_not_per_tick(free_port, wait_for):
    """An LA streamed at 50 Hz and polled at 10 Hz: its follow frames have no reply, so only
    its poll replies bring new values. No two consecutive states are the same reading with
    the same values, and there are no more states than replies (the old code published one
    per follow tick)."""
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600)
    simulator.start()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = config_for(simulator.port, endpoint)
    # A margin that leaves room for a poll between two ticks (50 ms would stop the polls).
    config["buses"][0] |= {"reply_margin_ms": 10, "devices": [
        {"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 10, "follow_period_ms": 20}]}
    daemon = Daemon(config)
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    states: list[dict] = []
    try:
        connected(client)
        subscriber = client.declare_subscriber(
            "busgate/gw1/dev/la1/state", lambda s: states.append(json.loads(s.payload.to_bytes())))
        wait_for(lambda: states)
        mark = len(simulator.recorder.records)
        states.clear()
        for position in range(500, 1500, 10):  # two seconds of targets, one every 20 ms
            client.put("busgate/gw1/dev/la1/follow", json.dumps({"position": position}))
            time.sleep(0.02)
        subscriber.undeclare()  # before the stream goes stale: its event publishes a state
        records = simulator.recorder.records[mark:]
    finally:
        client.close()
        daemon.shutdown()
        simulator.stop()
    ticks = sum(r.frame == "FollowCommand" for r in records)
    replies = sum(r.direction == "tx" for r in records)
    assert ticks > 50 and replies >= 10, (ticks, replies)
    repeated = [(a, b) for a, b in itertools.pairwise(states) if same_but_age(a, b)]
    assert repeated == [], "a state published again with the same ts and values"
    # A state that arrived just after ``mark`` may be a reply's from before it.
    assert len(states) <= replies + 2, f"{len(states)} states for {replies} replies, {ticks} ticks"
    assert len({s["position"] for s in states}) > 5, "the actuator followed"
