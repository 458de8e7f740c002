"""Joints on the wire: the gateway's API (without zenoh) on simulated buses whose devices have
joint tables. Nothing beyond a limit reaches a device on any path; a refused command sends
nothing; a follow step becomes a ramp at max_velocity, a speed step one at max_acceleration;
the joint op and the joint follow payloads speak SI."""

from __future__ import annotations

import itertools
import json
import math
import time

import can
import pytest

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.zlac706_common import rpm_from_speed_raw
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.bus.clock import now
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.ds_servo import DsServoDevice
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import parse_config
from tests.conftest import wait_until
from tests.wire_frames import received, written, written_speed

TURN = 2 * math.pi
_channels = itertools.count()
#: la1: 5 µm a count, 1–8 mm, at most 10 mm/s (40 counts a 20 ms tick).
GRIPPER = {"name": "gripper_left", "unit": "m", "scale": 5e-6, "min": 0.001, "max": 0.008,
           "max_velocity": 0.01}
#: la2: flipped, 10 mm at raw 0; limits the device's own.
FLIPPED = {"unit": "m", "scale": -5e-6, "offset": 0.01}
#: s1: one turn in 4096 counts, 0.5–5 rad.
WRIST = {"name": "wrist", "unit": "rad", "scale": TURN / 4096, "min": 0.5, "max": 5.0}
#: wheel: a velocity joint, at most 1 turn a second, 1 turn a second².
WHEEL = {"name": "left_wheel", "unit": "rad", "scale": TURN / 10_000, "max_velocity": TURN,
         "max_acceleration": TURN}


@pytest.fixture(scope="module")
def gateway():
    la_sim = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    ds_sim = SerialSimulator(ds, [DsServoDevice(1)], baudrate=1_000_000)
    channel = f"test-joints-{next(_channels)}"
    can_sim = CanSimulator(zcan, [Zlac706CanDevice(5, heartbeat_ms=50)],
                           bus=can.Bus(interface="virtual", channel=channel))
    for simulator in (la_sim, ds_sim, can_sim):
        simulator.start()
    config = parse_config({"gateway": {"name": "gw"}, "buses": [
        {"name": "uart0", "transport": "serial", "port": la_sim.port, "baudrate": 921_600,
         "reply_margin_ms": 50, "devices": [
             {"name": "la1", "kind": "inspire_la", "id": 1, "joint": GRIPPER},
             {"name": "la2", "kind": "inspire_la", "id": 2, "joint": FLIPPED}]},
        {"name": "uart1", "transport": "serial", "port": ds_sim.port, "baudrate": 1_000_000,
         "reply_margin_ms": 50, "devices": [{"name": "s1", "kind": "ds_servo", "id": 1,
                                             "joint": WRIST}]},
        {"name": "can0", "transport": "can", "interface": "virtual", "channel": channel,
         "reply_margin_ms": 50, "devices": [{"name": "wheel", "kind": "zlac706", "id": 5,
                                             "heartbeat_ms": 50, "joint": WHEEL}]}]})
    events = []
    runners = {bus.name: build_bus(bus, on_event=events.append).start() for bus in config.buses}
    api = GatewayApi("gw", runners, on_event=events.append)
    deadline = time.monotonic() + 20
    while not all(d.online for _, d in api.devices.values()) and time.monotonic() < deadline:
        time.sleep(0.02)
    yield api, {"uart0": la_sim, "uart1": ds_sim, "can0": can_sim}, events
    for runner in runners.values():
        runner.stop()
    for simulator in (la_sim, ds_sim, can_sim):
        simulator.stop()


def ask(api: GatewayApi, device: str, command: dict) -> dict:
    return api.command(device, json.dumps(command).encode()).result(10)


def accepted(api: GatewayApi, device: str, command: dict) -> dict:
    reply = ask(api, device, command)
    assert reply["ok"], reply
    return reply


def la_targets(simulator, since: int) -> list[tuple[str, int, int]]:
    """(frame, id, position) of every target the LA simulator received since ``since``."""
    return [(record.frame, target.device_id, target.position_raw)
            for record, frame in received(simulator, since, la)
            for target in getattr(frame, "targets", None) or [frame]
            if hasattr(target, "position_raw")]


def speeds(can_sim, since: int) -> list[float]:
    """Every speed written to the wheel since ``since``, rpm."""
    return [rpm_from_speed_raw(speed) for _, frame in received(can_sim, since, zcan)
            if (speed := written_speed(frame)) is not None]


def ramp_of(written: list[float]) -> list[float]:
    """The speeds in the order each was first written: a later write of one already written
    is the keep-alive's (it repeats the last speed the drive acknowledged, and runs when acks
    were late for its period, as on a loaded host), never a new target."""
    return list(dict.fromkeys(written))


@pytest.mark.parametrize(("device", "command", "words"), [
    ("la1", {"op": "move", "position": 1700}, "joint gripper_left: position 0.0085 m is beyond "
                                              "its max 0.008 m"),
    ("la1", {"op": "move", "position": 100}, "beyond its min 0.001 m"),
    ("la1", {"op": "follow", "position": 1999}, "beyond its max"),
    ("la1", {"op": "write", "index": 55, "data": "a406"}, "position 0.0085 m"),  # 1700
    ("la1", {"op": "write", "index": 55, "data": "06"}, "target_position is 2 bytes at 55"),
    ("la1", {"op": "group_move", "targets": [{"id": 2, "position": 5}, {"id": 1, "position": 5}]},
     "joint gripper_left"),
    ("la1", {"op": "joint", "position": 0.0081}, "position 0.0081 m is beyond its max 0.008 m"),
    ("s1", {"op": "move", "position": 4000}, "joint wrist: position 6.13592 rad is beyond its max"),
    ("s1", {"op": "goto_preset", "n": 1}, "cannot know"),
    ("s1", {"op": "write", "address": 20, "data": "0400"}, "cannot know"),  # the centre moved
    ("s1", {"op": "write", "address": 28, "data": "01"}, "cannot know"),  # a motor may spin
    ("s1", {"op": "write", "address": 9, "data": "0bb8"}, "cannot know"),  # targets clamped up
    ("s1", {"op": "write", "address": 11, "data": "0100"}, "cannot know"),  # and down
    ("s1", {"op": "reset"}, "cannot know"),  # the factory centre and angle limits again
    ("s1", {"op": "joint", "position": 0.2}, "beyond its min 0.5 rad"),
])  # fmt: skip
def test_a_command_beyond_a_limit_is_refused_and_sends_nothing(gateway, device, command, words):
    api, simulators, _ = gateway
    simulator = simulators["uart0" if device.startswith("la") else "uart1"]
    before = len(simulator.recorder.received())
    reply = ask(api, device, command)
    assert not reply["ok"] and reply["error"]["code"] == "out_of_range", reply
    assert words in reply["error"]["message"]
    accepted(api, device, {"op": "status"} if device.startswith("la") else {"op": "ping"})
    sent = {r.frame for r in simulator.recorder.received()[before:]}
    assert sent <= {"ControlCommand", "Ping", "ReadCommand", "Read"}, sent


def test_a_bus_group_move_is_judged_by_each_devices_joint(gateway):
    api, simulators, _ = gateway
    before = len(simulators["uart0"].recorder.received())
    payload = {"op": "group_move", "targets": [{"device": "la2", "position": 1900},
                                               {"device": "la1", "position": 1900}]}
    reply = api.bus_command("uart0", json.dumps(payload).encode()).result(10)
    assert reply["error"]["code"] == "out_of_range" and "gripper_left" in reply["error"]["message"]
    accepted(api, "la1", {"op": "status"})
    assert la_targets(simulators["uart0"], before) == []


def test_the_joint_op_moves_in_si_and_answers_with_the_joint(gateway):
    api, simulators, _ = gateway
    before = len(simulators["uart0"].recorder.received())
    reply = accepted(api, "la1", {"op": "joint", "position": 0.005})
    assert reply["joint"]["name"] == "gripper_left" and reply["joint"]["unit"] == "m"
    assert reply["state"]["joint"] == reply["joint"] and reply["state"]["target"] == 1000
    assert la_targets(simulators["uart0"], before) == [("MoveCommand", 1, 1000)]
    # The flipped joint: 10 mm at raw 0, so 2 mm is raw 1600.
    accepted(api, "la2", {"op": "joint", "position": 0.002})
    assert la_targets(simulators["uart0"], before)[-1] == ("MoveCommand", 2, 1600)
    wrong = ask(api, "la1", {"op": "joint", "velocity": 0.001})
    assert wrong["error"]["code"] == "bad_command" and "position joint" in wrong["error"]["message"]
    both = ask(api, "la1", {"op": "joint", "position": 0.005, "velocity": 0.0})
    assert both["error"]["code"] == "bad_command"


def test_the_joint_op_is_judged_by_the_claims_as_its_kinds_own_command(gateway):
    """The holder's joint command moves its device; another client's is refused ``claimed``;
    one sent with ``require_claim`` by a client that holds no claim is refused ``not_claimed``,
    and neither sends a frame."""
    api, simulators, _ = gateway
    simulator = simulators["uart0"]
    accepted(api, "la1", {"op": "claim", "client": "alice", "ttl_s": 5})
    try:
        before = len(simulator.recorder.received())
        accepted(api, "la1", {"op": "joint", "position": 0.004, "client": "alice"})
        assert la_targets(simulator, before) == [("MoveCommand", 1, 800)]
        before = len(simulator.recorder.received())
        other = ask(api, "la1", {"op": "joint", "position": 0.006, "client": "bob"})
        assert other["error"]["code"] == "claimed" and "alice" in other["error"]["message"]
        unheld = ask(api, "la2", {"op": "joint", "position": 0.004, "client": "bob",
                                  "require_claim": True})  # fmt: skip
        assert unheld["error"]["code"] == "not_claimed", unheld
        assert la_targets(simulator, before) == []
    finally:
        accepted(api, "la1", {"op": "release", "client": "alice"})


def test_info_and_states_carry_the_joint(gateway):
    api, *_ = gateway
    devices = {d["name"]: d for bus in api.info()["buses"] for d in bus["devices"]}
    assert devices["la1"]["joint"]["min"] == 0.001 and devices["la1"]["joint"]["configured"]
    assert devices["wheel"]["joint"]["type"] == "velocity"
    assert devices["wheel"]["joint"]["raw_per_turn"] == 10_000
    state = accepted(api, "s1", {"op": "ping"})["state"]
    assert state["joint"]["name"] == "wrist"
    assert state["joint"]["position"] == pytest.approx(state["position"] * TURN / 4096)


def test_a_follow_step_becomes_a_ramp_at_max_velocity_and_is_told_once(gateway):
    api, simulators, events = gateway
    accepted(api, "la1", {"op": "joint", "position": 0.002})  # raw 400
    simulator = simulators["uart0"]
    before, told = len(simulator.recorder.received()), len(events)
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:  # a client sends a step to 8.5 mm: past the limit
        assert api.follow("la1", b'{"joint": 0.0085, "client": "c1"}') is None
        time.sleep(0.01)
    api.command("la1", b'{"op": "end_follow", "client": "c1"}').result(10)
    sent = [p for frame, _, p in la_targets(simulator, before) if frame.startswith("Follow")]
    assert sent[0] <= 400 + 40 and max(sent) == 1600  # held at the limit, 8 mm
    assert all(0 <= b - a <= 40 for a, b in itertools.pairwise([400, *sent]))
    limited = [e for e in events[told:] if e.type == "limited"]
    assert [(e.device, e.fields["joint"], e.fields["limit"]) for e in limited] == [
        ("la1", "gripper_left", "max")]


def test_a_speed_step_becomes_a_ramp_at_max_acceleration_and_a_fast_one_is_refused(gateway):
    api, simulators, events = gateway
    accepted(api, "wheel", {"op": "set_mode", "mode": "velocity"})
    accepted(api, "wheel", {"op": "enable"})
    too_fast = ask(api, "wheel", {"op": "joint", "velocity": 7.0})
    assert too_fast["error"]["code"] == "out_of_range"
    assert "left_wheel: velocity 7 rad/s is beyond its max_velocity 6.28319" in \
        too_fast["error"]["message"]
    assert ask(api, "wheel", {"op": "velocity", "rpm": 61})["error"]["code"] == "out_of_range"
    can_sim = simulators["can0"]
    for _ in range(3):  # a stream this host let go stale (stopped at once) is streamed again
        before, told = len(can_sim.recorder.received()), len(events)
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:  # a step to 3 turns a second: past max_velocity too
            assert api.follow("wheel", b'{"joint_velocity": 18.85, "client": "c2"}') is None
            time.sleep(0.01)
        written = speeds(can_sim, before)
        api.command("wheel", b'{"op": "end_follow", "client": "c2"}').result(10)
        accepted(api, "wheel", {"op": "enable"})  # answered once the end's stop went out
        if not any(e.type == "stream_stale" for e in events[told:] if e.device == "wheel"):
            break
    # 60 rpm/s at a 20 ms period: 1.2 rpm a tick, whole raw units truncated on the wire.
    assert written and written[0] <= 1.2 + 0.4 and max(written) <= 60, written
    steps = list(itertools.pairwise([0.0, *ramp_of(written)]))
    assert all(0 <= b - a <= 1.2 + 0.4 for a, b in steps), written
    assert max(written) > 40  # 1 s of ramp reached most of the way to 60 rpm
    # A one-shot speed is a ramp too, from where the device was commanded (0 rpm: a stream
    # that ends stops the wheel at once), and it is kept.
    assert api.devices["wheel"][1].telemetry(0.0)["target_speed_rpm"] == 0
    before = len(can_sim.recorder.received())
    accepted(api, "wheel", {"op": "joint", "velocity": TURN / 2})  # 30 rpm: 25 ticks
    time.sleep(1.0)
    written = speeds(can_sim, before)
    # The ramp's last write is the drive's acknowledged speed, which its keep-alive repeats
    # (the last tick's reply is the wheel's though its stream ended as the tick was built).
    kept = api.devices["wheel"][1].telemetry(0.0)["target_speed_rpm"]
    accepted(api, "wheel", {"op": "disable"})
    assert kept == ramp_of(written)[-1] == written[-1], written
    assert written[0] <= 1.2 + 0.4 and written[-1] == pytest.approx(30, abs=0.4)
    assert all(0 <= b - a <= 1.2 + 0.4 for a, b in itertools.pairwise(ramp_of(written))), written
    assert len(written) >= 25


def test_a_stop_while_a_one_shot_speed_ramps_ends_the_ramp(gateway):
    """A disable while the ramp of a one-shot speed runs: its next ticks wrote speeds to the
    released drive (a preset its next enable would start the motor at), found by a review.
    The stop ends the ramp (``stream_stopped``); the drive gets 0 rpm and nothing more."""
    api, simulators, events = gateway
    can_sim = simulators["can0"]
    accepted(api, "wheel", {"op": "enable"})
    told = len(events)
    accepted(api, "wheel", {"op": "joint", "velocity": TURN / 2})  # 30 rpm: 25 ticks of ramp
    time.sleep(0.1)
    accepted(api, "wheel", {"op": "disable"})
    before = len(can_sim.recorder.received())
    time.sleep(0.2)
    assert set(speeds(can_sim, before)) <= {0}
    assert ("stream_stopped", {"reason": "stopped by a command"}) in [
        (e.type, e.fields) for e in events[told:] if e.device == "wheel"]


def test_a_speed_that_would_ramp_is_refused_while_the_motor_is_off(gateway):
    """A one-shot speed to a disabled wheel ramped the drive's preset at max_acceleration
    while the motor was off, and the enable then started the motor at the ramp's end at once
    (0 to 15 rad/s in one heartbeat, found by an audit). A speed its joint would ramp is
    refused until the motor is enabled, a stream's and a kept target's too: nothing is
    written."""
    api, simulators, _ = gateway
    can_sim = simulators["can0"]
    accepted(api, "wheel", {"op": "disable"})
    accepted(api, "wheel", {"op": "set_mode", "mode": "velocity"})
    before = len(can_sim.recorder.received())
    refused = ask(api, "wheel", {"op": "joint", "velocity": TURN / 2})
    assert refused["error"]["code"] == "bad_command", refused
    assert refused["error"]["message"].startswith(
        "joint left_wheel ramps its speeds at its max_acceleration from the speed the motor "
        "turns at, and the motor is off")
    assert ask(api, "wheel", {"op": "velocity", "rpm": 30})["error"]["code"] == "bad_command"
    followed = api.follow("wheel", b'{"joint_velocity": 3.0, "client": "c4"}')
    assert followed is not None and followed["error"]["code"] == "bad_command", followed
    kept = api.ramp_to("wheel", {"joint_velocity": 3.0}, "c4", 1.0)
    assert kept is not None and kept["error"]["code"] == "bad_command", kept
    time.sleep(0.2)
    assert speeds(can_sim, before) == []
    # A stop is no ramp: 0 rpm goes as it is, as a base's before its enable (a review's).
    accepted(api, "wheel", {"op": "velocity", "rpm": 0})
    assert speeds(can_sim, before) == [0]
    assert api.follow("wheel", b'{"joint_velocity": 0, "client": "c4"}') is None
    api.command("wheel", b'{"op": "end_follow", "client": "c4"}').result(10)


def test_a_one_shot_speed_that_would_ramp_is_refused_while_the_wheel_plays(gateway):
    """A one-shot speed to a wheel that plays (a trajectory, a base's drive) became a ramp
    that took turns with the play's ticks setting its speed, and the play's next tick then
    jumped back past max_acceleration (found by an audit, on a base's wheel). It is refused
    ``busy`` and nothing of it reaches the wire: every speed written is the play's."""
    api, simulators, _ = gateway
    can_sim = simulators["can0"]
    accepted(api, "wheel", {"op": "set_mode", "mode": "velocity"})
    accepted(api, "wheel", {"op": "enable"})
    runner = api.devices["wheel"][0]
    # from rest to 6 rpm at its max_acceleration (60 rpm/s): a step is refused (plays rule 6)
    runner.play({"wheel": lambda t_s: {"rpm": min(6.0, 60.0 * t_s)}}, now())
    try:
        wait_until(lambda: runner.plays.playing("wheel"))
        time.sleep(0.15)  # at 6 rpm
        before = len(can_sim.recorder.received())
        for command in ({"op": "joint", "velocity": TURN / 2}, {"op": "velocity", "rpm": -30}):
            refused = ask(api, "wheel", command)
            assert refused["error"]["code"] == "busy", refused
            assert "wheel plays a trajectory or drives a base" in refused["error"]["message"]
        time.sleep(0.2)
        written = speeds(can_sim, before)
        assert written and all(speed == pytest.approx(6, abs=0.2) for speed in written), written
        # A stop is not refused for the play (a review's): it goes as it is, and the play's
        # next tick overrides it. (This bus has no room for it beside the ticks: its reply
        # margin, for a loaded host, reserves each tick's exchange.)
        stop = ask(api, "wheel", {"op": "velocity", "rpm": 0})
        assert stop["ok"] or "plays a trajectory" not in stop["error"]["message"], stop
    finally:
        runner.stop_playing("wheel", speed=True)
        accepted(api, "wheel", {"op": "disable"})


def test_a_wheel_in_absolute_position_mode_streams_positions_held_by_its_joint(gateway):
    """A ZLAC706 in absolute position mode follows positions (its target register, 16): a
    step becomes a ramp within the joint's max_velocity (200 pulses a 20 ms tick) and
    max_acceleration (4 pulses a tick more each tick), from where the wheel is; a speed is
    refused while it follows positions, and nothing writes a speed."""
    api, simulators, events = gateway
    for command in ({"op": "disable"}, {"op": "set_mode", "mode": "position"},
                    {"op": "set_position_mode", "relative": False}, {"op": "enable"}):
        accepted(api, "wheel", command)
    can_sim = simulators["can0"]
    try:
        here = api.devices["wheel"][1].telemetry(0.0)["position"]
        before, told = len(can_sim.recorder.received()), len(events)
        step = json.dumps({"position": here + 3000, "client": "c3"}).encode()
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            assert api.follow("wheel", step) is None
            time.sleep(0.01)
        refused = api.follow("wheel", b'{"joint_velocity": 1.0, "client": "c3"}')
        assert "needs velocity mode" in refused["error"]["message"], refused
        api.command("wheel", b'{"op": "end_follow", "client": "c3"}').result(10)
        frames = [frame for _, frame in received(can_sim, before, zcan)]
    finally:
        accepted(api, "wheel", {"op": "disable"})
        accepted(api, "wheel", {"op": "set_mode", "mode": "velocity"})
    positions = [p for f in frames if (p := written(f, zcan.CanRegister.TARGET_POSITION))
                 is not None]
    assert not [f for f in frames if written_speed(f) is not None]
    moves = [b - a for a, b in itertools.pairwise([here, *positions])]
    assert len(positions) >= 25 and all(0 <= move <= 200 + 1 for move in moves), positions
    assert all(abs(b - a) <= 4 + 2 for a, b in itertools.pairwise([0, *moves])), moves
    assert positions[-1] > here + 1000  # 1 s of ramp at 4 pulses a tick² covers most of it
    limited = [e.fields["limit"] for e in events[told:] if e.type == "limited"]
    assert limited == ["max_acceleration"]
