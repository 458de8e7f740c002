"""Trajectories held to their devices' joints: a play in joint units (SI positions,
velocities, accelerations and tolerances) converted to each device's raw units by its
calibration, a negative scale included, and every play, raw or joint, checked whole against
the joint's limits (its position limits between the points too, ``max_velocity`` and
``max_acceleration`` on every segment's derivatives, a speed's own limits) and refused
``out_of_range`` naming the joint, the limit and the value, with nothing on the wire.

The gateway is in this process: three Inspire LA actuators on one pty (``la1``: joint
``gripper_left``, m, scale 1e-5, limited in position, velocity and acceleration; ``la2``:
``gripper_right``, a negative scale with an offset; ``la3``: no table, a raw joint) and a
ZLAC706 velocity joint on python-can's virtual bus (``wheel``: ``wheel_left``, rad, with a
``max_velocity`` and a ``max_acceleration``), driven through ``GatewayApi`` and
``Trajectories`` as ``tests/test_trajectory_wire.py`` drives them. The derivative bounds
themselves are a hypothesis property of the pure ``bounds``."""

from __future__ import annotations

import itertools
import json
import math
import time
from collections.abc import Iterator
from dataclasses import astuple, dataclass

import can
import pytest

from busgate.client.trajectories import play_body
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.errors import RefusedError
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.gateway.trajectory.checks import members_of, start_at_of
from busgate.gateway.trajectory.interpolation import Knot, paths_of
from busgate.gateway.trajectory.lanes import answer
from busgate.gateway.trajectory.playing import Trajectories
from busgate.schemas.config import CanBus, SerialBus
from busgate.schemas.joints import Joint, JointTable
from busgate.schemas.trajectory import TRAJECTORY_COMMAND_ADAPTER, TrajectoryPlay
from busgate.schemas.validation import describe_validation_error, refusal_code
from tests.conftest import wait_until
from tests.wire_frames import no_base, received, tick_targets, written_speed

BASE = "busgate/gw"
MARGIN_MS = 10  # as tests/test_trajectory_wire.py: room for the polls between ticks
PERIOD = 0.02
ROUND_S = 0.005
LA_IDS = {"la1": 1, "la2": 2, "la3": 3}
WHEEL_ID = 5
#: One pulse of the hub motor in radians (10000 a turn).
RAD_PER_PULSE = 2 * math.pi / 10_000
JOINTS = {
    "la1": {"name": "gripper_left", "unit": "m", "scale": 1e-5, "min": 0.0, "max": 0.015,
            "max_velocity": 0.05, "max_acceleration": 1.0},
    "la2": {"name": "gripper_right", "unit": "m", "scale": -1e-5, "offset": 0.02,
            "min": 0.005, "max": 0.02},
}  # fmt: skip
WHEEL_JOINT = {"name": "wheel_left", "type": "velocity", "unit": "rad",
               "scale": RAD_PER_PULSE, "max_velocity": 10.0, "max_acceleration": 20.0}  # fmt: skip

_ids = itertools.count()
_channels = itertools.count()


@dataclass
class World:
    api: GatewayApi
    runners: dict[str, BusRunner]
    la_sim: SerialSimulator
    can_sim: CanSimulator


@pytest.fixture(scope="module")
def world() -> Iterator[World]:
    la_sim = SerialSimulator(la, [InspireLaDevice(i) for i in LA_IDS.values()], baudrate=921_600)
    channel = f"test-joints-{next(_channels)}"
    can_sim = CanSimulator(zcan, [Zlac706CanDevice(WHEEL_ID, heartbeat_ms=50)],
                           bus=can.Bus(interface="virtual", channel=channel))  # fmt: skip
    for simulator in (la_sim, can_sim):
        simulator.start()
    devices = [{"name": name, "kind": "inspire_la", "id": ident}
               | ({"joint": JOINTS[name]} if name in JOINTS else {})
               for name, ident in LA_IDS.items()]  # fmt: skip
    buses = [
        SerialBus(name="uart0", transport="serial", port=la_sim.port, baudrate=921_600,
                  reply_margin_ms=MARGIN_MS, devices=devices),
        CanBus(name="can0", transport="can", interface="virtual", channel=channel,
               reply_margin_ms=MARGIN_MS,
               devices=[{"name": "wheel", "kind": "zlac706", "id": WHEEL_ID,
                         "heartbeat_ms": 50, "joint": WHEEL_JOINT}]),
    ]  # fmt: skip
    runners = {bus.name: build_bus(bus).start() for bus in buses}
    try:
        api = GatewayApi("gw", runners)
        wait_until(lambda: all(driver.online for _, driver in api.devices.values()))
        yield World(api, runners, la_sim, can_sim)
    finally:
        for runner in runners.values():
            runner.stop()
        for simulator in (la_sim, can_sim):
            simulator.stop()


class Player:
    """The trajectory key of the world's gateway, its loop part called each round."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.published: list[tuple[str, dict]] = []
        self.trajectories = Trajectories(world.api, BASE, self._publish, lambda event: None,
                                         no_base)

    def _publish(self, key: str, body: dict) -> None:
        self.published.append((key, body))

    def ask(self, command: dict) -> dict:
        return answer(self.trajectories.command, json.dumps(command).encode())

    def messages(self, trajectory: str) -> list[dict]:
        key = f"{BASE}/trajectory/{trajectory}/feedback"
        return [body for published, body in self.published if published == key]

    def result(self, trajectory: str) -> dict | None:
        found = [body for body in self.messages(trajectory) if "result" in body]
        return found[0] if found else None

    def feedback(self, trajectory: str) -> list[dict]:
        return [body for body in self.messages(trajectory) if "result" not in body]

    def finished(self, trajectory: str, timeout: float = 5.0) -> dict:
        deadline = time.monotonic() + timeout
        while (result := self.result(trajectory)) is None:
            assert time.monotonic() < deadline, "no result in time"
            self.trajectories.tick()
            time.sleep(ROUND_S)
        return result


@pytest.fixture
def player(world) -> Iterator[Player]:
    player = Player(world)
    yield player
    for running in player.ask({"op": "status"})["trajectories"]:  # a test that failed midway
        player.ask({"op": "cancel", "id": running["id"]})


def play_of(devices: list[str], points: list[dict], **fields) -> dict:
    return {"op": "play", "id": f"j{next(_ids)}", "devices": devices, "points": points,
            "start_at": time.time() + 0.1, **fields}  # fmt: skip


def command(world: World, device: str, fields: dict) -> dict:
    reply = world.api.command(device, json.dumps(fields).encode()).result(5)
    assert reply["ok"], reply
    return reply


def la_ticks(world: World, since: int) -> list[dict[int, int]]:
    """Each trajectory tick the LA bus received after its ``since``-th frame: each
    actuator's target, by id."""
    found = (tick_targets(frame) for _, frame in received(world.la_sim, since, la))
    return [targets for targets in found if targets is not None]


def speed_writes(world: World, since: int) -> list[int]:
    """The speed writes the ZLAC706 received after its ``since``-th frame (raw values)."""
    found = (written_speed(frame) for _, frame in received(world.can_sim, since, zcan))
    return [speed for speed in found if speed is not None]


def marks(world: World) -> tuple[int, int]:
    return len(world.la_sim.recorder.received()), len(world.can_sim.recorder.received())


def assert_refused_and_silent(world: World, player: Player, play: dict, code: str) -> str:
    """``play`` is refused with ``code`` and nothing of it reaches either bus, past the start
    it would have had (a later exchange on each bus answered): its message."""
    la_mark, can_mark = marks(world)
    reply = player.ask(play)
    assert not reply["ok"] and reply["error"]["code"] == code, reply
    assert player.ask({"op": "status"})["trajectories"] == []
    wait_until(lambda: time.time() > play["start_at"] + 3 * PERIOD)
    command(world, "la1", {"op": "status"})
    assert la_ticks(world, la_mark) == []
    assert speed_writes(world, can_mark) == []
    assert player.published == []
    return reply["error"]["message"]


def start_si(world: World, device: str) -> float:
    """Where a play would start ``device`` now, in its joint's SI units."""
    probe = TrajectoryPlay.model_validate(play_of([device], [{"t_s": 1.0, "positions": [0]}]))
    [member] = members_of(world.api, probe)
    return member.driver.joint.position_si(member.path.knots[0].value)


# -- conversion ----------------------------------------------------------------------------------


def test_joint_points_become_raw_knots_by_each_calibration_a_negative_scale_included():
    declaration = InspireLaDriver.joint_declaration()
    left = Joint.of("la1", declaration, JointTable(unit="m", scale=1e-5))
    right = Joint.of("la2", declaration, JointTable(unit="m", scale=-1e-5, offset=0.02))
    play = TrajectoryPlay.model_validate({
        "op": "play", "id": "p", "devices": ["la1", "la2"], "units": "joint",
        "interpolation": "quintic",
        "points": [{"t_s": 0.5, "positions": [0.005, 0.012], "velocities": [0.01, 0.01],
                    "accelerations": [0.1, -0.2]}]})  # fmt: skip
    la1, la2 = paths_of(play, [0.0, 300.0], [left, right])
    assert la1.knots[0] == Knot(0.0, 0.0) and la2.knots[0] == Knot(0.0, 300.0)  # starts: raw
    assert astuple(la1.knots[1]) == pytest.approx((0.5, 500.0, 1000.0, 10_000.0))
    assert astuple(la2.knots[1]) == pytest.approx((0.5, 800.0, -1000.0, 20_000.0))
    with pytest.raises(ValueError, match="joint"):
        paths_of(play, [0.0, 0.0])


def test_a_joint_play_reaches_the_wire_as_the_calibrations_raw_targets(world, player):
    """la1 (scale 1e-5) to 0.005 m is 500; la2 (scale -1e-5, offset 0.02) to 0.012 m is 800:
    the last tick carries both, every tick before is on the way there, and the feedback
    carries the values raw and again in SI."""
    starts = {name: start_si(world, name) for name in ("la1", "la2")}
    la_mark, _ = marks(world)
    play = play_of(["la1", "la2"], [{"t_s": 0.3, "positions": [0.005, 0.012]}], units="joint",
                   goal_tolerance=[0.0005, 0.0005], goal_time_s=2.0)  # fmt: skip
    reply = player.ask(play)
    assert reply["ok"], reply
    result = player.finished(play["id"])
    assert result["result"] == "succeeded", (result.get("reason"), result)
    ticks = la_ticks(world, la_mark)
    assert ticks and ticks[-1] == {1: 500, 2: 800}
    raw_starts = {1: round(starts["la1"] / 1e-5), 2: round((starts["la2"] - 0.02) / -1e-5)}
    for ident, end in ((1, 500), (2, 800)):
        values = [tick[ident] for tick in ticks]
        low, high = sorted((raw_starts[ident], end))
        assert all(low <= v <= high for v in values)
        assert values == sorted(values, reverse=raw_starts[ident] > end)
    feedback = player.feedback(play["id"])
    assert feedback  # the first goes out on the first round after the play is accepted
    right = next(d for d in feedback[-1]["devices"] if d["device"] == "la2")
    assert right["joint"]["name"] == "gripper_right" and right["joint"]["unit"] == "m"
    assert right["joint"]["desired"] == pytest.approx(0.02 - 1e-5 * right["desired"])
    if right["error"] is not None:
        assert right["joint"]["error"] == pytest.approx(-1e-5 * right["error"])


def test_joint_tolerances_are_taken_in_si_and_held_raw(world):
    play = TrajectoryPlay.model_validate(play_of(
        ["la1", "la2"], [{"t_s": 1.0, "positions": [0.007, 0.012]}], units="joint",
        path_tolerance=[0.001, 0.002], goal_tolerance=[0.0005, 0.0001]))  # fmt: skip
    left, right = members_of(world.api, play)
    assert (left.path_tolerance, left.goal_tolerance) == pytest.approx((100, 50))
    assert (right.path_tolerance, right.goal_tolerance) == pytest.approx((200, 10))
    assert (left.path.knots[-1].value, right.path.knots[-1].value) == pytest.approx((700, 800))


# -- limits --------------------------------------------------------------------------------------


def test_an_overshoot_past_a_position_limit_between_points_is_refused_naming_the_joint(
    world, player
):
    """Both points within 0.015 m, the cubic between them past it: refused, nothing sent."""
    points = [{"t_s": 0.5, "positions": [0.0145], "velocities": [0.04]},
              {"t_s": 1.0, "positions": [0.0145]}]  # fmt: skip
    message = assert_refused_and_silent(
        world, player, play_of(["la1"], points, units="joint"), "out_of_range"
    )
    # a value of the path past the max (docs/trajectories.md's example), between the points
    assert message == "joint gripper_left: position 0.017 m at t=0.75 s is beyond its max 0.015 m"


def test_a_joint_point_beyond_its_limit_is_refused_not_clamped(world, player):
    message = assert_refused_and_silent(
        world, player,
        play_of(["la1", "la2"], [{"t_s": 0.2, "positions": [0.005, 0.0201]}], units="joint"),
        "out_of_range",
    )  # fmt: skip
    assert message == ("joint gripper_right: position 0.0201 m at t=0.2 s is beyond its max 0.02 m")


def test_a_segment_faster_than_max_velocity_is_refused(world, player):
    points = [{"t_s": 1.0, "positions": [0.014]}, {"t_s": 1.05, "positions": [0.001]}]
    message = assert_refused_and_silent(
        world, player, play_of(["la1"], points, units="joint"), "out_of_range"
    )
    assert message == (
        "joint gripper_left: velocity -0.26 m/s at t=1 s is beyond its max_velocity 0.05 m/s"
    )


def test_a_segment_past_max_acceleration_is_refused(world, player):
    """A rest-to-rest cubic of 2 mm in 0.1 s: 0.03 m/s at most, within max_velocity, but
    6 × 0.002 / 0.1² = 1.2 m/s² at its ends, past max_acceleration."""
    points = [{"t_s": 1.0, "positions": [0.007]}, {"t_s": 1.1, "positions": [0.009]}]
    message = assert_refused_and_silent(
        world, player, play_of(["la1"], points, units="joint", interpolation="cubic"),
        "out_of_range",
    )  # fmt: skip
    assert message.startswith("joint gripper_left: acceleration 1.2 m/s² at t=1")
    assert message.endswith(" is beyond its max_acceleration 1 m/s²")


def test_a_raw_play_is_held_to_its_joints_limits_too(world, player):
    """1600 is within the actuator's 0–2000, past the joint's 0.015 m (1500)."""
    message = assert_refused_and_silent(
        world, player, play_of(["la3", "la1"], [{"t_s": 0.2, "positions": [1000, 1600]}]),
        "out_of_range",
    )  # fmt: skip
    assert message == "joint gripper_left: position 0.016 m at t=0.2 s is beyond its max 0.015 m"


def test_a_raw_joint_is_limited_by_its_devices_range_in_raw_units(world, player):
    message = assert_refused_and_silent(
        world, player, play_of(["la3"], [{"t_s": 0.2, "positions": [2001]}]), "out_of_range"
    )
    assert message == "joint la3: position 2001 raw at t=0.2 s is beyond its max 2000 raw"


def test_a_first_point_at_0_is_a_step_held_to_max_velocity(world, player):
    """A point at t_s 0 replaces the start: a step sent in one period. 2 mm in 20 ms is
    0.1 m/s, past max_velocity; the same point a second on is a path, and accepted."""
    start = start_si(world, "la1")
    target = start + 0.002 if start < 0.0075 else start - 0.002
    points = [{"t_s": 0.0, "positions": [target]}, {"t_s": 1.0, "positions": [target]}]
    message = assert_refused_and_silent(
        world, player, play_of(["la1"], points, units="joint"), "out_of_range"
    )
    assert message.startswith("joint gripper_left: velocity ")
    assert "at t=0 s is beyond its max_velocity 0.05 m/s: the first point, at t_s 0" in message
    members_of(world.api, TrajectoryPlay.model_validate(
        play_of(["la1"], points[1:], units="joint")))  # fmt: skip


@pytest.fixture
def turning(world) -> Iterator[None]:
    command(world, "wheel", {"op": "set_mode", "mode": "velocity"})
    command(world, "wheel", {"op": "enable"})
    yield
    command(world, "wheel", {"op": "velocity", "rpm": 0})
    command(world, "wheel", {"op": "disable"})


def test_a_speed_play_past_max_velocity_is_refused(world, player, turning):
    """150 rpm is 15.7 rad/s: past the joint's 10 rad/s (95.5 rpm), though the drive takes
    it."""
    message = assert_refused_and_silent(
        world, player, play_of(["wheel"], [{"t_s": 2.0, "rpms": [150.0]}]), "out_of_range"
    )
    assert message == (
        f"joint wheel_left: velocity {150 * 2 * math.pi / 60:g} rad/s at t=2 s is beyond its "
        "max_velocity 10 rad/s"
    )


def test_a_speed_play_changing_faster_than_max_acceleration_is_refused(world, player, turning):
    """0 to 50 rpm (5.2 rad/s, within max_velocity) in 0.1 s is 52 rad/s²."""
    message = assert_refused_and_silent(
        world, player, play_of(["wheel"], [{"t_s": 0.1, "rpms": [50.0]}]), "out_of_range"
    )
    assert message.startswith("joint wheel_left: acceleration 52.3")
    assert message.endswith(" rad/s² at t=0 s is beyond its max_acceleration 20 rad/s²")


def test_a_speed_play_within_its_joints_limits_is_accepted(world, turning):
    play = TrajectoryPlay.model_validate(play_of(["wheel"], [{"t_s": 1.0, "rpms": [60.0]}]))
    [member] = members_of(world.api, play)
    assert member.speed and member.stream.follow == "rpm"
    assert member.value(0.5) == pytest.approx(30.0)


# -- the schema and the SDK ------------------------------------------------------------------------


def refused(value: dict) -> tuple[str, str]:
    with pytest.raises(ValueError) as caught:
        TRAJECTORY_COMMAND_ADAPTER.validate_python(value)
    error = caught.value
    return refusal_code(error), describe_validation_error(error)  # type: ignore[arg-type]


def test_units_default_to_raw_whose_positions_are_whole():
    raw = {"op": "play", "id": "p", "devices": ["la1"], "points": [{"t_s": 1, "positions": [5]}]}
    assert TrajectoryPlay.model_validate(raw).units == "raw"
    code, line = refused(raw | {"points": [{"t_s": 1, "positions": [5.5]}]})
    assert code == "bad_command" and "raw positions are whole numbers" in line
    joint = TrajectoryPlay.model_validate(
        raw | {"units": "joint", "points": [{"t_s": 1, "positions": [0.0055]}]}
    )
    assert joint.points[0].values == [0.0055]
    code, _ = refused(raw | {"units": "joint", "points": [{"t_s": 1, "positions": [2e9]}]})
    assert code == "out_of_range"
    code, _ = refused(raw | {"units": "metres"})
    assert code == "bad_command"


def test_a_joint_play_of_speeds_is_refused_saying_what_a_velocity_joint_takes():
    code, line = refused({"op": "play", "id": "p", "devices": ["wheel"], "units": "joint",
                          "points": [{"t_s": 1, "rpms": [5.0]}]})  # fmt: skip
    assert code == "bad_command"
    assert 'units "joint" moves positions' in line and '"joint_velocity": v' in line


def test_the_sdks_play_sends_units_only_when_given():
    points = [{"t_s": 1.0, "positions": [0.005]}]
    plain = play_body("c", "t", ["la1"], points, {"goal_time_s": 1.0})
    assert plain == {"op": "play", "id": "t", "devices": ["la1"], "points": points,
                     "goal_time_s": 1.0}  # fmt: skip
    joint = play_body("c", "t", ["la1"], points, {"units": "joint"})
    assert joint["units"] == "joint"
    TrajectoryPlay.model_validate(joint)


def test_a_velocity_joints_raw_driver_has_no_speed_limit():
    """Without a table the ZLAC706 is a raw joint: speeds only its drive's own range."""
    joint = Zlac706CanDriver("w", 5).joint
    assert joint.unit == "raw" and joint.max_velocity is None and joint.max_acceleration is None


def test_a_start_at_far_in_the_past_is_refused_in_a_line_of_words_not_hundreds_of_digits():
    """``-1e300`` is a float a client may send; it was printed to the millisecond."""
    with pytest.raises(RefusedError) as refused:
        start_at_of(-1e300)
    assert str(refused.value) == ("start_at -1e+300 is -1e+300 s from now: at least 20 ms ahead, "
                                  "for every bus to meet it")
    with pytest.raises(RefusedError, match=r"^start_at 5\.000 is -\d+\.\d{3} s from now"):
        start_at_of(5.0)
