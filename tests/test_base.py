"""A base on the wire: two simulated ZLAC706 on one virtual CAN bus, the real bus runner, the
gateway's API and its bases (without zenoh), a thread standing in for the loop's rounds. Both
wheels' speeds of a slot leave together, a step in twist becomes a ramp, the deadman ramps
both down after ``cmd_timeout_s``, claims hold between the base and its wheels both ways, the
e-stop stops the base, a wheel that leaves stops the other, and the odometry follows the
wheels' encoders."""

from __future__ import annotations

import itertools
import json
import math
import re
import threading
import time
from collections import deque
from itertools import pairwise

import can
import pytest

from busgate.codecs import zlac706_can as zcan
from busgate.codecs.zlac706_common import rpm_from_speed_raw
from busgate.errors import ConfigError
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.base.bases import Bases
from busgate.gateway.bus.clock import now
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.gateway.trajectory.playing import Trajectories
from busgate.schemas.config import parse_config
from busgate.schemas.events import EVENT_ADAPTER
from busgate.schemas.replies import REFUSALS, error_reply
from tests.wire_frames import received, written_speed

TURN = 2 * math.pi
#: Each wheel: 10000 pulses a turn, the right one mirrored; at most 3 turns a second.
LEFT = {"name": "left_wheel", "unit": "rad", "scale": TURN / 10_000, "max_velocity": 3 * TURN}
RIGHT = {"name": "right_wheel", "unit": "rad", "scale": -TURN / 10_000, "max_velocity": 3 * TURN}
BASE = {
    "name": "base",
    "left": "wl",
    "right": "wr",
    "wheel_radius_m": 0.0825,
    "track_m": 0.4,
    "max_linear_mps": 1.0,
    "max_angular_radps": 2.0,
    "max_linear_accel": 2.0,
    "max_angular_accel": 6.0,
    "cmd_timeout_s": 0.3,
}
_channels = itertools.count()


class NoTrajectories:
    """The trajectories of a gateway that plays none (bases on their own): a lock of its
    own, nothing playing."""

    def __init__(self) -> None:
        self.players = threading.Lock()

    def playing(self, device: str) -> str | None:
        return None


def config_of(bases: list[dict], channel: str = "x", **wheel_tables: dict | None):
    tables = {"wl": LEFT, "wr": RIGHT} | wheel_tables
    return parse_config(
        {
            "gateway": {"name": "gw"},
            "bases": bases,
            "buses": [
                {
                    "name": "can0",
                    "transport": "can",
                    "interface": "virtual",
                    "channel": channel,
                    "reply_margin_ms": 50,
                    "devices": [
                        {
                            "name": name,
                            "kind": "zlac706",
                            "id": i,
                            "heartbeat_ms": 20,
                            "joint": table,
                        }
                        for i, (name, table) in enumerate(tables.items(), 1)
                    ],
                }
            ],
        }
    )


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"left": "nothing"}, "bases[0].left: no device 'nothing' in the config's buses"),
        ({"name": "wl"}, "bases[0].name: 'wl' is a device's name too: name the base otherwise"),
        ({"right": "wl"}, "left and right are both 'wl'"),
        ({"max_linear_mps": 2.0}, "max_linear_mps 2 needs the wheels at 24.24 rad/s"),
        ({"max_angular_radps": 9.0}, "max_angular_radps 9 needs the wheels at 21.82 rad/s"),
        (
            {"left": "slow"},
            "max_linear_accel 2 needs the wheels at 24.24 rad/s² (2 / wheel_radius_m "
            "0.0825), but left wheel 'slow' reaches at most 10 rad/s²",
        ),
        (
            {"left": "slow", "max_linear_accel": 0.5},
            "max_angular_accel 6 needs the wheels at 14.55 rad/s²",
        ),
        ({"track_m": 1e-300}, "bases[0].track_m: Input should be greater than or equal to 0.001"),
    ],
)
def test_check_config_refuses_a_base_its_wheels_cannot_be(change, words) -> None:
    """Speeds and accelerations alike (``slow``: a wheel of 10 rad/s² at most)."""
    with pytest.raises(ConfigError, match=re.escape(words)):
        config_of([BASE | change], slow=LEFT | {"name": "slow", "max_acceleration": 10.0})


def test_the_drive_takes_each_wheels_limits_from_its_joint() -> None:
    """The slower wheel's ``max_velocity`` and ``max_acceleration`` bound both (the wheels
    alone, never started)."""
    config = config_of(
        [BASE | {"right": "slow"}], slow=RIGHT | {"name": "slow", "max_acceleration": 30.0}
    )
    runner = build_bus(config.buses[0])
    bases = Bases(
        config.bases,
        GatewayApi("gw", {"can0": runner}),
        lambda event: None,
        lambda name, odometry: None,
        NoTrajectories(),
        estop_reset_key="busgate/gw/estop/reset",
    )
    geometry = bases.bases["base"].drive.geometry
    assert (geometry.max_wheel, geometry.max_wheel_accel) == (3 * TURN, 30.0)


def test_a_wheel_in_two_bases_or_without_a_joint_in_rad_is_refused() -> None:
    with pytest.raises(ConfigError, match="'wl' is a wheel of base 'base' already"):
        config_of([BASE, BASE | {"name": "other", "right": "w3"}], w3=RIGHT | {"name": "w3"})
    with pytest.raises(ConfigError, match="must be a velocity joint in rad"):
        config_of([BASE], wr=None)


class World:
    """The bus, the API, the bases, and a thread doing the loop's rounds."""

    def __init__(self, **wheel_tables: dict) -> None:
        channel = f"test-base-{next(_channels)}"
        self.sim = CanSimulator(
            zcan,
            [Zlac706CanDevice(1, heartbeat_ms=20), Zlac706CanDevice(2, heartbeat_ms=20)],
            bus=can.Bus(interface="virtual", channel=channel),
        )
        self.sim.start()
        self.config = config = config_of([BASE], channel, **wheel_tables)
        self.events: deque = deque()
        self.states: deque = deque()
        self.odometry: list[dict] = []
        runner = build_bus(
            config.buses[0],
            on_event=self.events.append,
            on_state=lambda device, state: self.states.append((device, state)),
        )
        self.runner = runner.start()
        self.api = GatewayApi("gw", {"can0": runner}, on_event=self.events.append)
        # Wired as the bridge wires them: a play and a twist chosen under one lock.
        self.api.driven_by = lambda device: self.bases.driving_wheel(device)
        self.trajectories = Trajectories(
            self.api,
            "busgate/gw",
            lambda key, body: None,
            self.events.append,
            driven_by=self.api.driven_by,
        )
        self.bases = Bases(
            config.bases,
            self.api,
            self.events.append,
            lambda name, odometry: self.odometry.append(odometry),
            self.trajectories,
            estop_reset_key="busgate/gw/estop/reset",
        )
        self._stop = threading.Event()
        self._rounds = threading.Thread(target=self._loop, daemon=True)
        self._rounds.start()
        deadline = time.monotonic() + 20
        while not all(d.online for _, d in self.api.devices.values()):
            assert time.monotonic() < deadline, "the wheels did not come online"
            time.sleep(0.02)

    def _loop(self) -> None:
        while not self._stop.is_set():
            while self.states:
                self.bases.take_state(*self.states.popleft())
            self.bases.tick()
            self.trajectories.tick()
            time.sleep(0.005)

    def close(self) -> None:
        self._stop.set()
        self._rounds.join(2)
        self.runner.stop()
        self.sim.stop()

    def base(self, command: dict) -> dict:
        return self.bases.command("base", json.dumps(command).encode()).result(10)

    def wheel(self, device: str, command: dict) -> dict:
        return self.api.command(device, json.dumps(command).encode()).result(10)

    def speeds(self, since: int) -> list[tuple[float, int, float]]:
        """(when, node, rpm) of every speed write since the ``since``-th frame."""
        return [
            (record.start, frame.device_id, rpm_from_speed_raw(speed))
            for record, frame in received(self.sim, since, zcan)
            if (speed := written_speed(frame)) is not None
        ]

    def wait_rest(self) -> None:
        deadline = time.monotonic() + 10
        while self.bases.bases["base"].playing_since is not None:
            assert time.monotonic() < deadline, "the base did not come to rest"
            time.sleep(0.02)


@pytest.fixture(scope="module")
def world():
    made = World()
    yield made
    made.close()


def test_a_base_whose_wheels_ramp_their_speeds_is_enabled_at_0_rpm() -> None:
    """Wheels with a max_acceleration (as the shipped robot's): the base's enable sends each
    0 rpm before its enable, which a review found refused while the motor was off (a ramp
    there would run on the drive's preset), so that the enable answered an error. A stop is
    no ramp: 0 rpm goes as it is, then the enable."""
    ramped = World(wl=LEFT | {"max_acceleration": 50.0}, wr=RIGHT | {"max_acceleration": 50.0})
    try:
        for wheel in ("wl", "wr"):
            assert ramped.wheel(wheel, {"op": "disable"})["ok"]
        since = len(ramped.sim.recorder.received())
        reply = ramped.base({"op": "enable"})
        assert reply["ok"], reply
        assert [(node, rpm) for _, node, rpm in ramped.speeds(since)] == [(1, 0), (2, 0)]
        state = {name: ramped.api.devices[name][1].telemetry(0.0) for name in ("wl", "wr")}
        assert all(s["enabled"] and s["mode"] == "velocity" for s in state.values())
    finally:
        ramped.close()


def test_a_twist_to_a_base_whose_wheels_are_off_is_refused_naming_enable(world) -> None:
    assert world.wheel("wl", {"op": "disable"})["ok"]
    reply = world.base({"op": "twist", "linear": 0.2})
    assert reply["error"]["code"] == "bad_command"
    assert 'send {"op":"enable"} to the base first' in reply["error"]["message"]
    assert world.base({"op": "enable"})["ok"]
    state = {name: world.api.devices[name][1].telemetry(0.0) for name in ("wl", "wr")}
    assert all(s["enabled"] and s["mode"] == "velocity" for s in state.values())


def test_a_twist_ramps_both_wheels_together_and_the_deadman_ramps_them_down(world) -> None:
    assert world.base({"op": "enable"})["ok"]
    since = len(world.sim.recorder.received())
    reply = world.base({"op": "twist", "linear": 0.5, "angular": 0.0, "client": "teleop"})
    assert reply["ok"] and reply["base"]["target"] == {"linear": 0.5, "angular": 0.0}
    assert reply["base"]["client"] == "teleop"  # whose twist it drives
    world.wait_rest()
    at_rest = world.base({"op": "status"})["base"]
    assert (at_rest["driving"], at_rest["client"]) == (False, None)  # it drives nobody's now
    writes = world.speeds(since)
    left = [(t, rpm) for t, node, rpm in writes if node == 1]
    right = [(t, rpm) for t, node, rpm in writes if node == 2]
    # each slot: the left wheel's write, then the right's, mirrored (the play may end between
    # the two writes of its last slot, both at rest). How soon the right's follows is the
    # host's (the left's echo comes first; a loaded host delayed it 19 ms): benchmarks time it
    assert len(right) > 10
    partners = []
    for t_right, rpm_right in right:
        t_left, rpm_left = max((w for w in left if w[0] <= t_right), default=(-1.0, None))
        assert t_left >= 0, "a right wheel's write before any left one"
        assert rpm_right == pytest.approx(-rpm_left, abs=0.4)
        partners.append(t_left)
    assert len(set(partners)) == len(partners), "two right writes in one slot"
    alone = [rpm for t, rpm in left if t not in partners]
    assert len(alone) <= 1 and all(rpm == 0 for rpm in alone), alone
    ramp = [rpm for _, rpm in left]
    top = 0.5 / 0.0825 * 60 / TURN  # 57.9 rpm at 0.5 m/s
    step = 2.0 * 0.0202 / 0.0825 * 60 / TURN  # 2 m/s² for a 20.2 ms slot: 4.7 rpm
    assert max(ramp) == pytest.approx(top, abs=0.4)
    # a slot the host let pass (a tick over 1 ms late gives up the next) is a step of two
    assert all(
        abs(b - a) <= step * max(1, round((tb - ta) / 0.0202)) + 0.4
        for (ta, a), (tb, b) in pairwise(left)
    ), ramp
    assert ramp[0] <= step + 0.4 and ramp[-1] == 0
    # held for cmd_timeout_s (0.3 s) from the command, then down: the top is short-lived
    held = [t for t, rpm in left if rpm == pytest.approx(top, abs=0.4)]
    assert held and held[-1] - left[0][0] < 0.3 + 0.25 + 0.1
    assert any(e.type == "stream_stale" and e.device == "base" for e in world.events)


def test_claims_hold_between_the_base_and_its_wheels_both_ways(world) -> None:
    assert world.wheel("wr", {"op": "claim", "client": "teleop", "ttl_s": 30})["ok"]
    try:
        refused = world.base({"op": "twist", "linear": 0.1, "client": "nav"})
        assert refused["error"]["code"] == "claimed" and "teleop" in refused["error"]["message"]
        refused = world.base({"op": "claim", "client": "nav"})
        assert refused["error"]["code"] == "claimed"
        assert world.api.devices["wl"][0].authority.claims.holder("wl", time.monotonic()) is None
    finally:
        assert world.wheel("wr", {"op": "release", "client": "teleop"})["ok"]
    assert world.base({"op": "claim", "client": "nav", "ttl_s": 30})["ok"]
    try:
        for wheel in ("wl", "wr"):
            refused = world.wheel(wheel, {"op": "velocity", "rpm": 10, "client": "teleop"})
            assert refused["error"]["code"] == "claimed" and "nav" in refused["error"]["message"]
    finally:
        events = len(world.events)
        assert world.base({"op": "release", "client": "nav"})["released"] is True
    told = [(e.device, e.type, e.fields) for e in list(world.events)[events:]]
    assert ("base", "released", {"base": "base", "client": "nav"}) in told  # as a device's
    assert world.base({"op": "release", "client": "nav"})["released"] is False  # none held


def test_the_estop_stops_the_base_and_after_its_reset_the_base_starts_from_rest(
    world,
) -> None:
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "twist", "linear": 0.3, "duration_s": 5})["ok"]
    time.sleep(0.2)
    since = len(world.sim.recorder.received())
    for stopped in world.api.stop_every_bus():
        stopped.result(5)
    world.wait_rest()
    # Both wheels at 0 rpm before either is released: the base stops together.
    zero, release = "00fa001100000000", "00fa00100000000f"
    stop_frames = [f"00{i}#{data}" for data in (zero, release) for i in (1, 2)]
    sent = [r.wire for r in world.sim.recorder.received()[since:] if r.wire in stop_frames]
    assert sent == stop_frames
    assert any(e.type == "base_stopped" for e in world.events)
    refused = world.base({"op": "twist", "linear": 0.3})
    assert refused["error"]["code"] == "estopped"
    assert refused["error"]["message"] == (  # what the base takes, not the wheel's own op
        'base base: wheel wl is e-stopped: send {"op":"enable"} to the base to let it move '
        "again (or reset the e-stop: a put on busgate/gw/estop/reset)"
    )
    assert world.base({"op": "status"})["base"]["twist"] == {"linear": 0.0, "angular": 0.0}
    for reset in world.api.reset_every_bus("test")[0]:
        reset.result(5)
    # After the reset the next play starts from rest, not from the 0.3 m/s before the e-stop.
    assert world.base({"op": "enable"})["ok"]
    since = len(world.sim.recorder.received())
    assert world.base({"op": "twist", "linear": 0.01, "duration_s": 0.2})["ok"]
    time.sleep(0.2)
    rpms = [abs(rpm) for _, _, rpm in world.speeds(since)]
    assert rpms and max(rpms) < 1.5  # 0.01 m/s on wheels of 82.5 mm: 1.16 rpm
    world.base({"op": "stop"})
    world.wait_rest()


def _play(world: World, devices: list[str], rpms: float, trajectory: str = "spin") -> dict:
    """A trajectory from another client turning ``devices`` at ``rpms`` for 3 s."""
    points = [{"t_s": t, "rpms": [rpms] * len(devices)} for t in (2.0, 3.0)]
    play = {"op": "play", "id": trajectory, "client": "other", "devices": devices, "points": points}
    try:
        return world.trajectories.command(json.dumps(play).encode())
    except REFUSALS as exc:
        return error_reply(exc)


def test_a_trajectory_takes_no_wheel_of_a_driving_base(world) -> None:
    """Rule 3: a play naming one wheel of a base that drives it (no claim held) would turn
    the base on the spot; it is refused ``busy`` and the base drives on both wheels."""
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "twist", "linear": 0.3, "duration_s": 2, "client": "drv"})["ok"]
    events = len(world.events)
    try:
        for devices in (["wl"], ["wl", "wr"]):
            refused = _play(world, devices, -100.0)
            assert refused["error"]["code"] == "busy"
            assert refused["error"]["message"].startswith(
                "wl is a wheel of base base, which is driving it: stop the base and wait until "
                "it is at rest"
            )
        assert world.trajectories.playing("wl") is None
        assert world.bases.driving_wheel("wl") == "base"
        # A stream or a ROS command to the wheel is told what drives it, not a trajectory
        # (it was: "wl is playing a trajectory: cancel it first"; an audit)
        follow = b'{"rpm": 10, "client": "other"}'
        for refused in (
            world.api.follow("wl", follow),
            world.api.ramp_to("wl", {"joint_velocity": 1.0}, "ros2", 1.0),
        ):
            assert refused["error"]["code"] == "busy"
            assert refused["error"]["message"].startswith(
                "wl is a wheel of base base, which is driving it: stop the base first"
            ), refused
        assert not any(e.type == "base_stopped" for e in list(world.events)[events:])
    finally:
        world.base({"op": "stop", "client": "drv"})
        world.wait_rest()


class OnePlaying:
    """The gateway's trajectories as a base asks them (``bases.TrajectoryPlayers``), one
    playing ``wr``: this bus has no room for a trajectory's ticks beside the base's (its
    reply margin, 50 ms for a loaded host, reserves each tick's exchange)."""

    def __init__(self) -> None:
        self.players = threading.Lock()

    def playing(self, device: str) -> str | None:
        return "spin" if device == "wr" else None


def test_a_twist_takes_no_wheel_a_trajectory_plays(world) -> None:
    """Rule 3 the other way: a twist while a wheel plays a trajectory is refused ``busy``,
    naming it, and nothing moves."""
    assert world.base({"op": "enable"})["ok"]
    bases = Bases(
        world.config.bases,
        world.api,
        world.events.append,
        lambda name, odometry: None,
        OnePlaying(),
        estop_reset_key="busgate/gw/estop/reset",
    )
    since = len(world.sim.recorder.received())
    refused = bases.command("base", b'{"op":"twist","linear":0.2}').result(10)
    assert refused["error"]["code"] == "busy"
    assert "wheel wr plays trajectory 'spin': cancel it first" in refused["error"]["message"]
    assert bases.driving_wheel("wr") is None
    time.sleep(0.1)
    # nothing moves (a 0 rpm may be the last tick of the test before's play, at rest)
    assert [rpm for *_, rpm in world.speeds(since) if rpm] == []


def _wheel_2(world: World):
    return next(d for d in world.sim.devices if d.device_id == 2)


def _back_online(world: World) -> None:
    """Wheel 2 answers and heartbeats again; the base waits until it is back."""
    world.sim.faults.configure(silent_ids=frozenset())
    _wheel_2(world).heartbeat_s = 0.020
    deadline = time.monotonic() + 10
    while not world.api.devices["wr"][1].online:  # an init write answered, then a heartbeat
        assert time.monotonic() < deadline, "wr did not come back"
        time.sleep(0.02)


@pytest.mark.parametrize("heartbeats", [False, True], ids=["silent", "taking-no-write"])
def test_a_wheel_that_goes_offline_stops_the_base_at_once(world, heartbeats) -> None:
    """Rule 3 for a wheel whose node dies (silent: no heartbeat, no answer) or goes on
    reporting but answers none of its speed writes (heartbeats alone kept it online): both
    wheels are ramped to 0 long before the twist's 5 s, a ``base_stopped`` event names the
    wheel, and a twist while it is offline is refused naming it."""
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "twist", "linear": 0.3, "duration_s": 5})["ok"]
    time.sleep(0.3)
    events, started = len(world.events), time.monotonic()
    world.sim.faults.configure(silent_ids=frozenset({2}))
    if not heartbeats:
        _wheel_2(world).heartbeat_s = 0
    try:
        world.wait_rest()
        assert time.monotonic() - started < 2.0, "the base drove on with one wheel"
        news = [(e.device, e.type, e.fields) for e in list(world.events)[events:]]
        reason = "no reply" if heartbeats else "heartbeat lost"
        assert ("wr", "offline", {"reason": reason}) in news
        assert ("base", "base_stopped", {"base": "base", "wheel": "wr",
                                          "reason": "went offline"}) in news  # fmt: skip
        for device, kind, fields in news:  # as event.json describes them
            EVENT_ADAPTER.validate_python({"ts": 0.0, "device": device, "type": kind, **fields})
        time.sleep(0.6)  # the ramp (0.5 s) down
        left = [rpm for _, node, rpm in world.speeds(0) if node == 1]
        assert left[-1] == 0
        refused = world.base({"op": "twist", "linear": 0.3})
        assert refused["error"]["code"] == "device_timeout"
        assert refused["error"]["message"] == "base base: wheel wr is offline"
    finally:
        _back_online(world)


def _until(condition, what: str) -> None:
    deadline = time.monotonic() + 10
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def _faults_of(world: World, device: str) -> list[str]:
    return world.api.devices[device][1].telemetry(0.0)["faults"]


def _clear_fault(world: World) -> None:
    """Wheel 2's alarm reset as a client would (disable first: ``zlac706_state`` rule 6)."""
    assert world.wheel("wr", {"op": "disable"})["ok"]
    assert world.wheel("wr", {"op": "clear_alarm"})["ok"]
    _until(lambda: not _faults_of(world, "wr"), "wr's fault did not clear")
    assert world.base({"op": "enable"})["ok"]


def test_a_wheel_in_fault_refuses_a_twist_and_stops_a_driving_base(world) -> None:
    """Rule 3 for a wheel whose drive alarms (its power stage off): a twist is refused naming
    it and its fault, with nothing sent; one that faults while the base drives stops both."""
    assert world.base({"op": "enable"})["ok"]
    _wheel_2(world).inject_fault("over_current", now())
    try:
        _until(lambda: _faults_of(world, "wr"), "wr's fault was not reported")
        since = len(world.sim.recorder.received())
        refused = world.base({"op": "twist", "linear": 0.3, "angular": 0.0})
        assert refused["error"]["code"] == "bad_command"
        assert "wheel wr is in fault (over_current)" in refused["error"]["message"]
        assert (
            world.bases.twist("base", b'{"linear":0.3,"angular":0.0}')["error"] == refused["error"]
        )
        # the base's enable too (it answered ok, its power stage staying off)
        assert world.base({"op": "enable"})["error"] == refused["error"]
        time.sleep(0.1)
        # nothing moves (a 0 rpm may be what a wheel back from offline before is restored with)
        assert [rpm for *_, rpm in world.speeds(since) if rpm] == []
        assert world.bases.bases["base"].playing_since is None
    finally:
        _clear_fault(world)
    assert world.base({"op": "twist", "linear": 0.3, "angular": 0.0, "duration_s": 5})["ok"]
    time.sleep(0.3)
    events, started = len(world.events), time.monotonic()
    _wheel_2(world).inject_fault("over_current", now())
    try:
        world.wait_rest()
        assert time.monotonic() - started < 2.0, "the base drove on with one wheel"
        news = [(e.device, e.type, e.fields) for e in list(world.events)[events:]]
        assert (
            "base",
            "base_stopped",
            {"base": "base", "wheel": "wr", "reason": "in fault: over_current"},
        ) in news
        time.sleep(0.6)  # the ramp (0.5 s) down
        left = [rpm for _, node, rpm in world.speeds(0) if node == 1]
        assert left[-1] == 0
    finally:
        _clear_fault(world)


def test_a_base_at_rest_takes_no_wheel_from_a_speed_of_its_own() -> None:
    """Rule 3: the base's play starts from rest, and its first tick cut a wheel's own speed to
    0 at once (an audit: 76 to 0 rpm in one slot, past the wheel's max_acceleration). While
    the wheel's speed command ramps (a stream), a twist is refused ``busy``; once the wheel
    turns at its speed, the twist's play is refused when it reaches the bus (``plays`` rule
    6): ``base_stopped`` names the step, and the wheel's speed is untouched."""
    ramped = World(wl=LEFT | {"max_acceleration": 50.0}, wr=RIGHT | {"max_acceleration": 50.0})
    try:
        assert ramped.base({"op": "enable"})["ok"]
        assert ramped.wheel("wl", {"op": "velocity", "rpm": 76})["ok"]  # 0.16 s of ramp
        refused = ramped.base({"op": "twist", "linear": 0.05})
        assert refused["error"] == {
            "code": "busy",
            "message": (
                "base base: wheel wl follows a stream of its own (a client's follow key, or its "
                "speed command's ramp): the base starts from rest and would stop it at once; end "
                'it first ({"op":"end_follow"} to the wheel)'
            ),
        }
        _until(lambda: not ramped.runner.streams.following("wl"), "wl's ramp did not end")
        since, events = len(ramped.sim.recorder.received()), len(ramped.events)
        assert ramped.base({"op": "twist", "linear": 0.05, "duration_s": 1})["ok"]
        _until(
            lambda: any(e.type == "base_stopped" for e in list(ramped.events)[events:]),
            "the base did not stop",
        )
        stopped = next(e for e in list(ramped.events)[events:] if e.type == "base_stopped")
        assert stopped.fields["wheel"] == "wl"
        assert stopped.fields["reason"].startswith("would step -7.9")  # rad/s, from 76 rpm
        assert "from where its last command had sent it" in stopped.fields["reason"]
        time.sleep(0.1)
        assert [rpm for _, node, rpm in ramped.speeds(since) if node == 1] == []
    finally:
        ramped.close()


def test_the_client_that_enabled_the_base_going_stops_no_wheel_another_client_drives() -> None:
    """The base's enable sends each wheel 0 rpm as its caller: that made it each wheel's
    deadman, whose going then sent the wheels 0 rpm one-shot under another client's twist (an
    audit saw 58 -> 0 -> 54 rpm on the demo's wheels, which ramp their speeds: one wheel at 0
    and the other at full speed). A wheel the base plays is the play's: the going client
    stops nothing."""
    ramped = World(wl=LEFT | {"max_acceleration": 50.0}, wr=RIGHT | {"max_acceleration": 50.0})
    try:
        assert ramped.base({"op": "enable", "client": "enabler"})["ok"]
        assert ramped.base({"op": "twist", "linear": 0.3, "duration_s": 5, "client": "driver"})[
            "ok"
        ]
        time.sleep(0.6)  # at speed
        since, events = len(ramped.sim.recorder.received()), len(ramped.events)
        ramped.api.client_left("enabler")
        ramped.bases.client_left("enabler")
        time.sleep(0.3)
        speeds = [abs(rpm) for *_, rpm in ramped.speeds(since)]
        assert len(speeds) > 10 and min(speeds) > 30, speeds  # 34.7 rpm at 0.3 m/s
        assert [e for e in list(ramped.events)[events:] if e.type == "stopped"] == []
    finally:
        ramped.close()


def test_a_twist_while_the_wheels_ramp_down_after_base_stopped_is_refused_busy(world) -> None:
    """After a ``base_stopped`` the drive starts its next play from rest, while the wheels
    still ramp down from their speed: a twist then was taken, and the wheels' speed cut from
    78 to 4 rpm in one slot (an audit's wheel back online at once). It is refused ``busy``
    until they rest; then a twist starts from there."""
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "twist", "linear": 0.3, "duration_s": 5})["ok"]
    time.sleep(0.6)
    events = len(world.events)
    world.runner.stop_playing("wr", speed=True)  # it leaves the base's play, ramping
    _until(
        lambda: any(e.type == "base_stopped" for e in list(world.events)[events:]),
        "the base did not stop",
    )
    refused = world.base({"op": "twist", "linear": 0.3, "duration_s": 5})
    assert refused["error"] == {
        "code": "busy",
        "message": "base base: wheel wl still ramps to 0 after the base stopped (within 0.5 s): "
        "send the twist again once it rests",
    }
    _until(lambda: not world.runner.plays.playing("wl"), "wl did not come to rest")
    since = len(world.sim.recorder.received())
    assert world.base({"op": "twist", "linear": 0.3, "duration_s": 0.1})["ok"]
    world.wait_rest()
    first = next(rpm for _, node, rpm in world.speeds(since) if node == 1)
    assert first < 5  # from rest, at the base's acceleration (4.7 rpm a slot)


def test_a_twist_right_after_a_base_came_to_rest_is_taken(world) -> None:
    """Its play ends on the loop's thread, its wheels leave it on their bus threads a moment
    later: a twist between the two was refused as if the wheels still ramped down after a
    ``base_stopped`` (a review found it 5 times in 5)."""
    assert world.base({"op": "enable"})["ok"]
    base = world.bases.bases["base"]
    for _ in range(3):
        events = len(world.events)
        assert world.base({"op": "twist", "linear": 0.1, "duration_s": 0.05})["ok"]
        deadline = time.monotonic() + 10
        while base.playing_since is not None:  # no sleep: the window is a few ms
            assert time.monotonic() < deadline, "the base did not come to rest"
        again = world.base({"op": "twist", "linear": 0.1, "duration_s": 0.05})
        stopped = [e for e in list(world.events)[events:] if e.type == "base_stopped"]
        if stopped:  # a loaded host let a wheel's tick go by: then the refusal is the rule's
            assert again["error"]["code"] == "busy", (again, stopped)
            _until(
                lambda: not any(world.runner.plays.playing(w) for w in ("wl", "wr")),
                "the wheels did not rest",
            )
            continue
        assert again["ok"], again
        world.wait_rest()


def test_a_wheel_that_reboots_is_re_based_and_the_odometry_keeps_its_pose(world) -> None:
    """Rule 5: wheel 2's drive reboots while the base drives straight, its counter back at 0
    (from 2.6 rad: a step of 11 cm and half a radian in 20 ms when integrated); the pose
    goes on from where it was."""
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "reset_odometry"})["ok"]
    assert world.base({"op": "twist", "linear": 0.5, "angular": 0.0, "duration_s": 5})["ok"]
    time.sleep(0.5)
    told = len(world.odometry)
    _wheel_2(world).reboot(now())
    time.sleep(0.3)
    world.base({"op": "stop"})
    world.wait_rest()
    time.sleep(0.1)
    track = world.odometry[told - 1 :]
    # its drive off since (the simulated reboot): the other wheel turns the base, a
    # centimetre and a few hundredths of a radian a heartbeat at 0.5 m/s
    for a, b in pairwise(track):
        assert math.hypot(b["x"] - a["x"], b["y"] - a["y"]) < 0.03, track
        assert abs(math.remainder(b["theta"] - a["theta"], math.tau)) < 0.05, track
    assert world.base({"op": "enable"})["ok"]  # the rebooted drive's power stage again


def test_odometry_follows_the_wheels_encoders_and_resets(world) -> None:
    def pulses() -> tuple[int, int]:
        return tuple(world.api.devices[name][1].telemetry(0.0)["position"] for name in ("wl", "wr"))

    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "reset_odometry"})["ok"]
    time.sleep(0.1)
    told, before = len(world.odometry), pulses()
    since = len(world.sim.recorder.received())
    assert world.base({"op": "twist", "linear": 0.5, "duration_s": 1.0})["ok"]
    world.wait_rest()
    # a constant twist keeps each drive refreshed: a write at least every keep-alive period
    for node in (1, 2):
        times = [t for t, n, _ in world.speeds(since) if n == node]
        assert max(b - a for a, b in pairwise(times)) < 0.4, times
    time.sleep(0.2)
    last, after = world.odometry[-1], pulses()
    assert len(world.odometry) > told + 20  # at the heartbeats' rate
    # straight ahead, as far as the encoders say (the mirrored right motor counts down):
    # about 0.5 m (0.25 s up, 0.75 s at 0.5 m/s, 0.25 s down); on a loaded host less (a tick
    # late past its slot gives it up: CI saw 0.27 m while other tests ran), never more
    turned = [(b - a) * TURN / 10_000 for a, b in zip(before, after, strict=True)]
    travelled = 0.0825 * (turned[0] - turned[1]) / 2
    assert last["x"] == pytest.approx(travelled, abs=0.002)
    assert 0.2 < travelled < 0.6
    # the right wheel's write of each slot follows the left's by an exchange: a real, small
    # turn while the speed changes (the encoders say so), not the odometry's
    assert abs(last["y"]) < 0.01 and abs(last["theta"]) < math.radians(1)
    assert world.base({"op": "reset_odometry"})["ok"]
    time.sleep(0.1)
    assert abs(world.odometry[-1]["x"]) < 0.002


def test_a_claim_holder_powers_its_base_and_a_twist_sent_before_its_stop_is_dropped(world):
    assert world.base({"op": "claim", "client": "nav", "ttl_s": 30})["ok"]
    try:
        assert world.base({"op": "enable", "client": "nav"})["ok"]  # the wheels are nav's
        refused = world.base({"op": "enable", "client": "teleop"})
        assert refused["error"]["code"] == "claimed"  # (a disable, a stop, never is)
        told = len(world.events)
        twist = json.dumps({"linear": 0.3, "angular": 0.6, "client": "nav", "seq": 7}).encode()
        assert world.bases.twist("base", twist) is None
        time.sleep(0.1)  # on its way, the curvature asked for all along (``kinematics`` rule 3)
        sent = world.bases.bases["base"].drive.sent
        assert sent.linear > 0 and sent.angular == pytest.approx(2 * sent.linear)
        assert world.base({"op": "stop", "client": "nav", "seq": 9})["ok"]
        assert any(e.type == "stopped" for e in list(world.events)[told:])
        world.wait_rest()
        assert not any(e.type == "stream_stale" for e in list(world.events)[told:])
        for seq in (8, 9):  # sent before the stop, or numbered as it: dropped
            late = json.dumps({"linear": 0.3, "client": "nav", "seq": seq}).encode()
            assert world.bases.twist("base", late) is None
            assert world.bases.bases["base"].playing_since is None
        newer = json.dumps({"linear": 0.1, "client": "nav", "seq": 10}).encode()
        assert world.bases.twist("base", newer) is None
        assert world.bases.bases["base"].playing_since is not None
        assert world.base({"op": "stop", "client": "nav"})["ok"]
        world.wait_rest()
    finally:
        assert world.base({"op": "release", "client": "nav"})["ok"]


def _drive_until(world: World, linear: float, angular: float, reached) -> None:
    """Hold ``linear``/``angular`` until ``reached(odometry)``, then stop and wait for rest.
    Each twist holds 0.1 s: a host that stalls this loop (a CI host did, for a few hundred
    ms) lets the base run on that long at most before it ramps down."""
    deadline, reply = time.monotonic() + 30, None
    while not (world.odometry and reached(world.odometry[-1])):
        assert time.monotonic() < deadline, f"the base never got there; its last reply: {reply}"
        reply = world.base({"op": "twist", "linear": linear, "angular": angular, "duration_s": 0.1})
        time.sleep(0.02)
    world.base({"op": "stop"})
    world.wait_rest()


def _side(world: World, metres: float) -> None:
    start = world.odometry[-1]

    def along(o: dict) -> float:
        return math.hypot(o["x"] - start["x"], o["y"] - start["y"])

    # Each phase stops short of the side by more than it runs on when the loop stalls (0.1 s
    # at its speed, then its braking), so the last, slowest one decides where the base ends.
    _drive_until(world, 0.4, 0.0, lambda o: along(o) >= metres - 0.15)
    _drive_until(world, 0.1, 0.0, lambda o: along(o) >= metres - 0.02)
    _drive_until(world, 0.02, 0.0, lambda o: along(o) >= metres - 0.0006)


def _turn(world: World, radians: float) -> None:
    start = world.odometry[-1]["theta"]

    def turned(o: dict) -> float:
        return math.remainder(o["theta"] - start, math.tau)

    _drive_until(world, 0.0, 1.0, lambda o: turned(o) >= radians - 0.35)  # as ``_side``
    _drive_until(world, 0.0, 0.3, lambda o: turned(o) >= radians - 0.05)
    _drive_until(world, 0.0, 0.05, lambda o: turned(o) >= radians - 0.0008)


@pytest.mark.slow
def test_a_square_of_one_metre_sides_returns_to_its_start(world) -> None:
    """Driven by the odometry, as a client would: the simulated wheels follow their speeds
    with their ramps, and the pose integrated from their encoders comes back to the start
    within 2 cm and 2°."""
    assert world.base({"op": "enable"})["ok"]
    assert world.base({"op": "reset_odometry"})["ok"]
    time.sleep(0.2)
    for _ in range(4):
        _side(world, 1.0)
        _turn(world, math.pi / 2)
    end = world.odometry[-1]
    assert math.hypot(end["x"], end["y"]) < 0.02, end
    assert abs(math.remainder(end["theta"], math.tau)) < math.radians(2), end


def test_a_bug_under_a_twist_put_is_its_internal_refusal_not_lost(
    world, monkeypatch, caplog
) -> None:
    """A code review: only refusals were caught, so a bug under a twist put escaped to the
    intake's log line, and the flight recorder never kept the put with its answer."""

    def broken(*args) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(world.bases, "_drive", broken)
    with caplog.at_level("ERROR"):
        reply = world.bases.twist("base", b'{"linear":0.3}')
    assert reply == {"ok": False, "error": {"code": "internal", "message": "a bug"}}
    assert "base base: twist failed" in caplog.text and "RuntimeError: a bug" in caplog.text
