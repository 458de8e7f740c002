"""The ROS 2 face's pure parts: what a commands message asks of each joint (NaN and short lists
are no command, unknown names told once, velocity joints timed out on a fake clock), a ROS
trajectory as the gateway's command, and the diagnostics' levels."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import pytest

from busgate.errors import ConfigError, RefusedError
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.ros2.commands import UNKNOWN_KEPT, Commands, JointRef
from busgate.gateway.ros2.diagnostics import (
    ERROR,
    OK,
    STALE,
    WARN,
    BusHealth,
    Dropped,
    JointHealth,
    diagnostic_array,
)
from busgate.gateway.ros2.face import REFUSAL_TOLD_EVERY_S, Ros2Face
from busgate.gateway.ros2.node import Hushed
from busgate.gateway.ros2.trajectory import ROS_TRAJECTORY_ID, trajectory_command
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import parse_config

GRIPPER = JointRef("gripper", "la1", "position")
WHEEL = JointRef("wheel", "drive", "velocity")
JOINTS = {j.name: j for j in (GRIPPER, WHEEL)}
NOW = 1_700_000_000.0  # Unix seconds


def commands() -> Commands:
    return Commands(dict(JOINTS), timeout_s=0.5)


def test_each_joint_takes_its_interface_and_nan_or_inf_is_no_command() -> None:
    taken = commands().take({"name": ["gripper", "wheel"], "position": [0.004, math.nan],
                             "velocity": [-math.inf, 2.5]}, 0.0)
    assert [(t.joint.name, t.value, t.follow_fields) for t in taken.targets] == [
        ("gripper", 0.004, {"joint": 0.004}),
        ("wheel", 2.5, {"joint_velocity": 2.5}),
    ]
    assert taken.unknown == [] and taken.refused is None
    nan = commands().take({"name": ["gripper", "wheel"], "position": [math.nan, math.nan]}, 0.1)
    assert nan.targets == [] and nan.refused is None  # NaN for both, no velocity list
    assert commands().take({"name": ["wheel"], "velocity": [math.inf]}, 0.2).targets == []


def test_a_list_of_one_interface_only_goes_to_the_joints_of_that_interface_in_order() -> None:
    """ros2_control's topic-based system: each joint's command in its interface's list only."""
    taken = commands().take({"name": ["wheel", "gripper"], "position": [0.004],
                             "velocity": [1.5]}, 0.0)
    assert [(t.joint.name, t.value) for t in taken.targets] == [("gripper", 0.004),
                                                                ("wheel", 1.5)]
    assert taken.refused is None


@pytest.mark.parametrize(("message", "refusal"), [
    ({"name": ["gripper", "wheel"], "position": [0.007, 1.0]},
     "position given for velocity joint wheel"),
    ({"name": ["gripper", "wheel"], "position": [0.004, 9.0], "velocity": [1.0, 2.5]},
     "position given for velocity joint wheel"),
    ({"name": ["gripper"], "position": [math.nan], "velocity": [0.5]},
     "velocity given for position joint gripper"),
])
def test_a_joint_given_a_number_in_the_other_types_list_refuses_the_message(
        message, refusal) -> None:
    """The wheel's position was thrown away without a word while the gripper moved: a joint
    commanded through an interface it does not have refuses the message, as ros2_control's
    lists that say nothing certain do."""
    taken = commands()
    first = taken.take(message, 0.0)
    assert first.targets == [] and first.refused == (
        f"{refusal}: a joint takes only its type's list (NaN in the other for none)")
    assert taken.expired(10.0) == []


def test_a_list_that_cannot_say_whose_each_value_is_moves_nothing() -> None:
    more = {**JOINTS, "wrist": JointRef("wrist", "s1", "position")}
    taken = Commands(more, 0.5).take(
        {"name": ["gripper", "wrist", "wheel"], "position": [0.004], "velocity": [1.0]}, 0.0)
    assert taken.targets == []
    assert taken.refused == (
        "whose is each value? position has 1, velocity 1 values for 2 position and 1 velocity "
        "joints (each joint's command interface must be its type, or give every name a value, "
        "NaN for none)")


@pytest.mark.parametrize("message", [
    # ros2_control's topic-based system, the gripper state-only and a typo with its interface
    {"name": ["gripper", "gripper_x"], "position": [0.008], "velocity": []},
    {"name": ["wheel", "wheel_x"], "velocity": [3.0]},
    {"name": ["gripper_x", "gripper"], "position": [0.006], "velocity": [0.5]},
    # the wheel with no command interface (or a position one): whose is the one position?
    {"name": ["gripper", "wheel"], "position": [0.004]},
    {"name": ["gripper", "gripper", "wheel"], "position": [0.004], "velocity": [1.0]},
])
def test_lists_that_do_not_say_for_certain_whose_each_value_is_refuse_the_message(
        message) -> None:
    """A value meant for a name of no joint here (or for a joint of another interface) was
    given by its place to a joint it was not meant for: the gripper took 0.008 m meant for a
    misspelt joint, the wheel 3 rad/s."""
    taken = commands()
    first = taken.take(message, 0.0)
    assert first.targets == [] and first.refused.startswith("whose is each value? ")
    assert taken.expired(10.0) == []  # a refused velocity command is no command


def test_a_message_that_says_nothing_certain_is_refused_in_one_line_and_the_diagnostics(
        monkeypatch, caplog) -> None:
    api, bridge, face = gripper_face()
    monkeypatch.setattr(api, "ramp_to", lambda *_: pytest.fail("a refused message moved"))
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.ros2.face"):
        face._command({"name": ["gripper", "gripper_x"], "position": [0.008], "velocity": []})
    refusal = ("whose is each value? position has 1, velocity 0 values for 2 names, 1 of them "
               "no joint of this gateway (give every name a value, NaN for none)")
    assert [r.getMessage() for r in caplog.records] == [
        "ros2: a command names no joint of this gateway: 'gripper_x'",
        f"ros2: command for joint gripper refused: {refusal}"]
    assert bridge.soon == []
    [gripper] = [s for s in face.diagnostics()["status"] if s["name"].endswith("joint gripper")]
    assert {kv["key"]: kv["value"] for kv in gripper["values"]}["last_refusal"] == refusal


def commands_status(face: Ros2Face) -> tuple[int, str, dict[str, str]]:
    """The level, message and values of the face's ``<node>: commands`` status."""
    [status] = [s for s in face.diagnostics()["status"] if s["name"].endswith(": commands")]
    return status["level"], status["message"], {kv["key"]: kv["value"] for kv in status["values"]}


def told_then_a_second_later(caplog, hushed: Hushed, send: Callable[[], None],
                             times: int) -> tuple[list[str], list[str]]:
    """The face's warnings as ``send()`` comes ``times`` times, then once more a second
    later (``hushed``'s interval past)."""
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.ros2.face"):
        for _ in range(times):
            send()
        first = [r.getMessage() for r in caplog.records]
        hushed.told_at -= REFUSAL_TOLD_EVERY_S
        send()
    return first, [r.getMessage() for r in caplog.records]


def test_a_trajectory_naming_only_joints_the_gateway_lacks_is_told_and_shown(caplog) -> None:
    """A MoveIt trajectory with a misspelt joint plays nothing: its name is shown in the
    commands' diagnostics, as a command's (it was refused in silence); and every such
    trajectory is told refused, why and that it plays nothing, a line a second at most (the
    first was told only as an unknown name, the next not at all), its refusal naming it (the
    name's own line once made two lines of one message)."""
    _, _, face = gripper_face()
    message = {"joint_names": ["gripper_typo"],
               "points": [{"positions": [0.001], "time_from_start": {"sec": 1, "nanosec": 0}}]}
    refused = ("ros2: a trajectory refused, it plays nothing: no joint 'gripper_typo' on this "
               "gateway")
    first, then = told_then_a_second_later(
        caplog, face._trajectories_told, lambda: face._trajectory(message), 3)
    assert first == [refused]
    assert then[-1] == f"{refused} (2 more since the last such line)"
    level, said, values = commands_status(face)
    assert level == WARN and "'gripper_typo'" in said
    assert values["last_refusal"] == "trajectory: no joint 'gripper_typo' on this gateway"
    # one the play refuses: told as a trajectory's, shown in the joint's status
    face._trajectories_told.told_at -= REFUSAL_TOLD_EVERY_S
    face._trajectory_answered(["gripper"], {"ok": False, "error": {"message": "la1 is e-stopped"}},
                              cancel=False)
    assert caplog.records[-1].getMessage() == (
        "ros2: a trajectory refused, it plays nothing: la1 is e-stopped")
    assert face._refusals["gripper"] == "trajectory: la1 is e-stopped"


def test_a_command_naming_no_joint_is_refused_in_one_line_and_the_commands_status(
        monkeypatch, caplog) -> None:
    """Values without names were refused in silence: no line, no diagnostics (no joint's
    status to show it in). Told a line a second at most, shown until a command is taken."""
    api, bridge, face = gripper_face()
    monkeypatch.setattr(api, "ramp_to", lambda *_: pytest.fail("a refused message moved"))
    nameless = {"name": [], "position": [0.003], "velocity": [1.0]}
    refusal = ("whose is each value? position has 1, velocity 1 values for no names (name "
               "their joints)")
    line = ("ros2: a command naming no joint of this gateway refused, nothing in it moves: "
            f"{refusal}")
    first, then = told_then_a_second_later(
        caplog, face._nameless_told, lambda: face._command(nameless), 4)
    assert first == [line]
    assert then == [line, f"{line} (3 more since the last such line)"]
    assert bridge.soon == []
    assert commands_status(face) == (
        WARN, f"a message naming no joint of this gateway refused: {refusal}",
        {"unknown_joints": "", "last_refusal": refusal})
    face._command({"name": ["gripper"], "position": [0.003]})  # taken: the refusal is past
    assert commands_status(face) == (OK, "ok", {"unknown_joints": "", "last_refusal": ""})


def test_an_empty_joint_name_is_shown_in_quotes() -> None:
    """An empty name read as nothing: ``commands name unknown joints: , elbow``."""
    _, _, face = gripper_face()
    face._command({"name": ["", "elbow", "gripper"], "position": [1.0, 1.0, 0.002]})
    level, said, values = commands_status(face)
    assert (level, said) == (WARN, "commands name unknown joints: '', 'elbow'")
    assert values["unknown_joints"] == "'', 'elbow'"


def test_an_unknown_name_is_told_once_and_the_rest_is_taken() -> None:
    taken = commands()
    first = taken.take({"name": ["elbow", "gripper"], "position": [1.0, 0.002]}, 0.0)
    assert first.unknown == ["elbow"] and [t.joint for t in first.targets] == [GRIPPER]
    again = taken.take({"name": ["elbow"], "position": [1.0]}, 0.1)
    assert again.unknown == again.targets == [] and again.refused is None


def test_unknown_names_are_kept_cut_and_no_more_than_unknown_kept() -> None:
    """A peer may name any number of joints, of any length: the log and /diagnostics keep at
    most ``UNKNOWN_KEPT`` of them, each cut as a refusal repeats a name."""
    taken = commands()
    names = [f"{n}:" + "x" * 10_000 for n in range(100)] + ["gripper"]
    first = taken.take({"name": names, "position": [1.0] * 100 + [0.002]}, 0.0)
    assert len(first.unknown) == UNKNOWN_KEPT < 100
    assert all(len(name) <= 65 and name.endswith("…") for name in first.unknown)
    assert taken.unknown == set(first.unknown)
    assert [t.joint for t in first.targets] == [GRIPPER], "the known joint is taken all the same"


def test_a_silent_velocity_joint_is_due_a_stop_once_and_a_position_joint_never() -> None:
    taken = commands()
    taken.take({"name": ["gripper", "wheel"], "position": [0.004, math.nan],
                "velocity": [math.nan, 1.0]}, 0.0)
    assert taken.expired(0.5) == []
    assert taken.expired(0.51) == [WHEEL]
    assert taken.expired(5.0) == []  # told once per silence
    taken.take({"name": ["wheel"], "velocity": [1.0]}, 6.0)
    taken.forget(["wheel"])  # stopped otherwise (an e-stop)
    assert taken.expired(7.0) == []


def test_a_refused_command_of_a_turning_velocity_joint_leaves_its_stop_due() -> None:
    """An audit: a velocity joint turning at one command, its next refused (2e9 rad/s), was
    forgotten: no stop came, and it turned with no end. Refused, a joint that never moved
    is due no stop; one that turns keeps its stop, timed from its last command."""
    taken = commands()
    taken.take({"name": ["wheel"], "velocity": [1.0]}, 0.0)
    taken.refused("wheel", 0.0)  # its first command: it never moved
    assert taken.expired(1.0) == []
    taken.take({"name": ["wheel"], "velocity": [1.0]}, 2.0)
    taken.carried_out("wheel")
    taken.take({"name": ["wheel"], "velocity": [2e9]}, 2.2)
    taken.refused("wheel", 2.2)
    assert taken.expired(2.6) == []
    assert taken.expired(2.71) == [WHEEL]
    taken.take({"name": ["wheel"], "velocity": [1.0]}, 3.0)
    taken.refused("wheel", 3.0)  # stopped since: it turned no more
    assert taken.expired(9.0) == []
    # A review: the next command taken (another thread) while the first was refused; the
    # refusal must not forget the next one's stop
    taken.take({"name": ["wheel"], "velocity": [1.0]}, 10.0)
    taken.take({"name": ["wheel"], "velocity": [2.0]}, 10.01)
    taken.refused("wheel", 10.0)
    taken.carried_out("wheel")
    assert taken.expired(100.0) == [WHEEL]


def point(seconds: float, positions: list[float], **fields: list[float]) -> dict:
    whole, fraction = divmod(seconds, 1)
    return {"positions": positions, "time_from_start": {"sec": int(whole),
            "nanosec": round(fraction * 1e9)}} | fields


def test_a_ros_trajectory_is_a_joint_play_interpolated_by_the_fields_it_gives() -> None:
    message = {"joint_names": ["gripper"], "points": [point(0.5, [0.002]), point(1.25, [0.004])]}
    command = trajectory_command(message, JOINTS, "ros2", NOW)
    assert command == {"op": "play", "id": ROS_TRAJECTORY_ID, "client": "ros2",
                       "devices": ["la1"], "units": "joint",
                       "points": [{"t_s": 0.5, "positions": [0.002]},
                                  {"t_s": 1.25, "positions": [0.004]}]}
    message["points"] = [point(1, [0.002], velocities=[0.0], accelerations=[0.0]),
                         point(2, [0.004], velocities=[0.0], accelerations=[0.0])]
    message["header"] = {"stamp": {"sec": 1_700_000_000, "nanosec": 500_000_000}}
    command = trajectory_command(message, JOINTS, "ros2", NOW)
    assert command["interpolation"] == "quintic" and command["start_at"] == 1_700_000_000.5
    for now in (NOW + 0.5, NOW + 0.4):  # a stamp past, or too near to keep: now
        assert "start_at" not in trajectory_command(message, JOINTS, "ros2", now)
    assert command["points"][1] == {"t_s": 2.0, "positions": [0.004], "velocities": [0.0],
                                    "accelerations": [0.0]}
    message["points"][1].pop("velocities")  # not on every point: not used
    assert "velocities" not in trajectory_command(message, JOINTS, "ros2", NOW)["points"][0]


def test_an_empty_trajectory_cancels_and_a_joint_it_cannot_move_is_refused() -> None:
    assert trajectory_command({"joint_names": ["gripper"], "points": []}, JOINTS, "ros2",
                              NOW) == {
        "op": "cancel", "id": ROS_TRAJECTORY_ID, "client": "ros2"}
    with pytest.raises(RefusedError, match="elbow"):
        trajectory_command({"joint_names": ["elbow"], "points": [point(1, [0])]}, JOINTS, "r",
                           NOW)
    with pytest.raises(RefusedError, match="velocity joint"):
        trajectory_command({"joint_names": ["wheel"], "points": [point(1, [0])]}, JOINTS, "r",
                           NOW)


def health(state: dict | None, **fields) -> JointHealth:
    return JointHealth(**({"joint": "gripper", "device": "la1", "hardware_id": "la1",
                           "state": state, "claimed_by": None, "refusal": None} | fields))


@pytest.mark.parametrize(("joint", "level", "message"), [
    (health(None), STALE, "no reading"),
    (health({"online": False, "stale": True}), ERROR, "offline"),
    (health({"online": True, "stale": False, "estopped": True}), ERROR, "e-stopped"),
    (health({"online": True, "stale": False, "faults": ["overheat"]}), ERROR, "faults: overheat"),
    (health({"online": True, "stale": True}), STALE, "reading stale"),
    (health({"online": True, "stale": False}, claimed_by="teleop",
            refusal="la1 is claimed by 'teleop'"), WARN,
     "command refused: la1 is claimed by 'teleop'"),
    (health({"online": True, "stale": False}), OK, "ok"),
])
def test_a_joints_level_is_its_worst_reason(joint, level, message) -> None:
    [status, _, _] = diagnostic_array("node", {"sec": 1, "nanosec": 2}, [joint], [])["status"]
    assert (status["level"], status["message"]) == (level, message)
    assert status["name"] == "node: joint gripper"
    values = {kv["key"]: kv["value"] for kv in status["values"]}
    assert values["claimed_by"] == (joint.claimed_by or "")


def test_unknown_joint_names_are_a_warning_of_the_commands_status() -> None:
    statuses = diagnostic_array("n", {"sec": 0, "nanosec": 0}, [], [], {"elbow", "arm"})
    assert [(s["name"], s["level"], s["message"]) for s in statuses["status"]] == [
        ("n: commands", WARN, "commands name unknown joints: 'arm', 'elbow'"),
        ("n: input", OK, "ok")]
    quiet = diagnostic_array("n", {"sec": 0, "nanosec": 0}, [], [])["status"][-2]
    assert (quiet["level"], quiet["message"]) == (OK, "ok")


def test_what_the_node_dropped_is_a_warning_of_the_input_status_the_second_it_came() -> None:
    """The node counted what it dropped (a sample without rmw_zenoh's attachment, not its
    type's CDR) and said it in a warning a minute at most: no ROS user saw it."""
    commands = Dropped("robot_joint_commands", 5, 2, "a sample without rmw_zenoh's attachment")
    estop = Dropped("~/reset_estop", 1, 0, "a request on 0/x/**, not the service's key")
    [*_, status] = diagnostic_array("n", {"sec": 0, "nanosec": 0}, [], [], (),
                                    [commands, estop])["status"]
    assert (status["name"], status["level"], status["message"]) == (
        "n: input", WARN, "dropped in the last second: robot_joint_commands: 2, the last a "
        "sample without rmw_zenoh's attachment")
    assert {kv["key"]: kv["value"] for kv in status["values"]} == {
        "dropped": "6",
        "dropped on robot_joint_commands": "5, the last a sample without rmw_zenoh's attachment",
        "dropped on ~/reset_estop": "1, the last a request on 0/x/**, not the service's key"}
    quiet = diagnostic_array("n", {"sec": 0, "nanosec": 0}, [], [], (), [estop])["status"][-1]
    assert (quiet["level"], quiet["message"]) == (OK, "ok")


def test_a_bus_is_an_error_when_down_and_a_warning_when_it_erred() -> None:
    stats = {"utilisation": 0.25, "timeouts": 3, "smallest_gap_s": None}
    levels = [s["level"] for s in diagnostic_array("n", {"sec": 0, "nanosec": 0}, [], [
        BusHealth("uart0", False, stats, 0), BusHealth("uart1", True, stats, 2),
        BusHealth("can0", True, stats, 0)])["status"]]
    assert levels == [ERROR, WARN, OK, OK, OK]
    [up, _, _] = diagnostic_array("n", {"sec": 0, "nanosec": 0}, [],
                               [BusHealth("can0", True, stats, 0)])["status"]
    assert {kv["key"]: kv["value"] for kv in up["values"]} == {
        "up": "true", "utilisation": "0.25", "timeouts": "3"}


def test_a_joint_named_again_and_again_is_one_target_its_last_value() -> None:
    """A message naming the gripper 100,000 times made 100,000 ramps, one after another on
    zenoh's thread (an e-stop waited behind them for seconds)."""
    taken = commands().take({"name": ["gripper"] * 100_000,
                             "position": [0.001] * 99_999 + [0.002]}, NOW)
    assert [(t.joint.name, t.value) for t in taken.targets] == [("gripper", 0.002)]


class HandingOnBridge:
    """What the face asks of the bridge here: a hand-over to the loop (kept, run by hand), an
    e-stop and its reset (nothing to stop: no bus runs; the resets' clients kept)."""

    def __init__(self) -> None:
        self.soon: list = []
        self.resets: list = []
        self.at_estop: list = []
        self.kept: list[str] = []  # the devices a reset leaves to another client's claim
        self.events: list = []

    def call_soon(self, function, *args) -> None:
        self.soon.append((function, args))

    def estop(self, client, key) -> list:
        for forget in self.at_estop:  # as the bridge's, once every bus has it
            forget()
        return []

    def estop_reset(self, client) -> tuple[list, list[str]]:
        self.resets.append(client)
        return [], self.kept

    def run_soon(self) -> None:
        soon, self.soon = self.soon, []
        for function, args in soon:
            function(*args)


def face_on(device: dict, baudrate: int) -> tuple[GatewayApi, HandingOnBridge, Ros2Face]:
    """A face on a gateway of ``device`` alone, whose bus is built, never started."""
    config = parse_config({
        "gateway": {"name": "gw1"}, "ros2": {},
        "buses": [{"name": "bus0", "transport": "serial", "port": "/dev/null",
                   "baudrate": baudrate, "devices": [device]}],
    })
    api = GatewayApi("gw1", {"bus0": build_bus(config.buses[0])})
    bridge = HandingOnBridge()
    return api, bridge, Ros2Face(config.ros2, api, bridge)  # type: ignore[arg-type]


def gripper_face() -> tuple[GatewayApi, HandingOnBridge, Ros2Face]:
    """A face on a gateway of one LA, joint ``gripper``."""
    return face_on({"name": "la1", "kind": "inspire_la", "id": 1,
                    "joint": {"name": "gripper", "unit": "m", "scale": 5e-6}}, 921_600)


def test_a_velocity_joint_turning_when_its_next_command_is_refused_is_stopped_in_time(
        monkeypatch):
    """An audit: ``drive`` turning at a command carried out, its next refused, turned with
    no end (the refusal forgot it: no stop was due). Its stop comes ``command_timeout_s``
    after that command, as after any."""
    api, bridge, face = face_on({"name": "drive", "kind": "zlac706", "id": 1, "joint": {
        "name": "wheel", "unit": "rad", "scale": 0.0006283185307179586}}, 115_200)
    ramps: list = []
    too_fast = {"ok": False, "error": {"code": "out_of_range", "message": "too fast"}}
    monkeypatch.setattr(api, "ramp_to", lambda device, fields, *_: ramps.append(fields) or (
        too_fast if fields["joint_velocity"] > 100 else None))
    face._command({"name": ["wheel"], "velocity": [1.0]})
    bridge.run_soon()
    face._command({"name": ["wheel"], "velocity": [2e9]})
    bridge.run_soon()
    assert ramps == [{"joint_velocity": 1.0}, {"joint_velocity": 2e9}]
    face._stop_silent_joints(time.monotonic() + face.section.command_timeout_s + 0.1)
    assert ramps[2:] == [{"joint_velocity": 0.0}]


@pytest.mark.parametrize("estop", ["service", "zenoh"])
def test_a_command_due_when_the_estop_comes_is_dropped_and_the_next_one_goes(monkeypatch, estop):
    """Commands are handed to the loop, each joint's latest alone; any e-stop, the face's
    service or the zenoh API's, drops what is due, so that nothing sent before it moves a
    joint after the reset (a flood held such a command back until 7 s after the reset, which
    then moved the joint)."""
    api, bridge, face = gripper_face()
    bridge.at_estop.append(face._forget_before_estop)  # as ``open`` does
    ramps: list = []
    monkeypatch.setattr(api, "ramp_to", lambda device, fields, *_: ramps.append((device, fields)))
    for position in (0.001, 0.002, 0.003):  # three messages before the loop's turn
        face._command({"name": ["gripper"], "position": [position]})
    assert len(bridge.soon) == 1  # one hand-over for them all
    if estop == "service":
        face._estop({})
    else:
        bridge.estop("teleop", "busgate/gw1/estop")
    bridge.run_soon()
    assert ramps == []
    face._command({"name": ["gripper"], "position": [0.004]})
    face._command({"name": ["gripper"], "position": [0.005]})
    bridge.run_soon()
    assert ramps == [("la1", {"joint": 0.005})]


def test_a_command_taken_before_an_estop_is_never_handed_on_after_it(monkeypatch):
    """The loop takes what is due from the lock, then ramps each: an e-stop counted in
    between (its forgetting came too early for them) still stops them."""
    api, bridge, face = gripper_face()
    ramps: list = []
    monkeypatch.setattr(api, "ramp_to", lambda device, fields, *_: ramps.append((device, fields)))
    face._command({"name": ["gripper"], "position": [0.001]})
    api.estops += 1  # an e-stop handed to the buses, its forgetting not yet run
    bridge.run_soon()
    assert ramps == []
    face._command({"name": ["gripper"], "position": [0.002]})
    bridge.run_soon()
    assert ramps == [("la1", {"joint": 0.002})]


def test_a_joints_refusals_are_logged_once_a_second_however_their_words_change(caplog):
    """A refusal was logged again whenever its text differed from the last: commands whose
    position list alternated between two wrong lengths logged 20,000 lines for 10,000."""
    _, bridge, face = gripper_face()
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.ros2.face"):
        for n in range(100):
            face._refused(["gripper"], f"refusal {n % 2}")
        assert [r.getMessage() for r in caplog.records] == [
            "ros2: command for joint gripper refused: refusal 0"]
        assert face._refusals["gripper"] == "refusal 1"  # the diagnostics say the latest
    face._reset_estop({})
    assert bridge.resets == ["ros2"]  # told through the bridge's reports, as the key's reset


def test_a_refusal_of_several_joints_is_one_line(caplog) -> None:
    """A message naming several joints logged its refusal once for each."""
    _, _, face = gripper_face()
    face.joints["wheel"] = WHEEL
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.ros2.face"):
        face._refused(["wheel", "elbow", "wheel", "gripper"], "one message's refusal")
    assert [r.getMessage() for r in caplog.records] == [
        "ros2: command for joints wheel, gripper refused: one message's refusal"]


def ros2_config(ros2: dict, bases: list | None = None):
    """A gateway ``arm-2`` of four wheels, with ``ros2`` as its ``[ros2]`` and ``bases``."""
    wheels = [{"name": side, "kind": "zlac706", "id": n,
               "joint": {"name": f"{side}_joint", "unit": "rad", "scale": 6.28e-4 * sign}}
              for n, (side, sign) in enumerate(
                  (("wl", 1), ("wr", -1), ("wl2", 1), ("wr2", -1)), start=1)]
    return parse_config({
        "gateway": {"name": "arm-2"}, "ros2": ros2,
        "buses": [{"name": "can0", "transport": "can", "interface": "virtual",
                   "channel": "unused", "devices": wheels}],
        "bases": bases or [],
    })


BASE = {"name": "base", "left": "wl", "right": "wr", "wheel_radius_m": 0.1, "track_m": 0.4,
        "max_linear_mps": 1.0, "max_angular_radps": 2.0, "max_linear_accel": 2.0,
        "max_angular_accel": 4.0}


@pytest.mark.parametrize(("ros2", "bases", "why"), [
    ({"namespace": "/robot", "reset_estop": "~/estop"}, [],
     "ros2.reset_estop: '~/estop' is /robot/busgate_arm_2/estop, as ros2.estop is"),
    ({"joint_states": "robot_joint_commands"}, [],
     "ros2.joint_commands: 'robot_joint_commands' is /robot_joint_commands, as "
     "ros2.joint_states is"),
    ({"node": "n", "estop": "/n/stop", "reset_estop": "~/stop"}, [],
     "ros2.reset_estop: '~/stop' is /n/stop, as ros2.estop is"),
    ({"odom": "/diagnostics"}, [BASE], "ros2.odom: '/diagnostics' is /diagnostics, as "
     "ros2.diagnostics is"),
])
def test_two_names_of_the_table_that_come_to_one_entity_are_refused(ros2, bases, why) -> None:
    """An e-stop call on a key that is also the reset's ran both, in no set order; a
    subscription on the joint states' topic took the gateway's own states for commands."""
    with pytest.raises(ConfigError) as refused:
        ros2_config(ros2, bases)
    assert why in str(refused.value)


@pytest.mark.parametrize(("diagonal", "why"), [
    ([0.001] * 5, "at least 6 items"),
    ([0.001] * 7, "at most 6 items"),
    ([0.001] * 5 + [-0.01], "greater than or equal to 0"),
    ([0.001] * 5 + [math.nan], "finite number"),
    ([0.001] * 5 + ["0.01"], "valid number"),
])
def test_an_odometry_covariance_diagonal_that_is_no_six_variances_is_refused(
        diagonal, why) -> None:
    for key in ("pose_covariance_diagonal", "twist_covariance_diagonal"):
        with pytest.raises(ConfigError) as refused:
            ros2_config({key: diagonal}, [BASE])
        assert f"ros2.{key}" in str(refused.value) and why in str(refused.value)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_a_timeout_that_is_no_finite_number_is_told_so(value) -> None:
    """An audit: NaN was refused as "less than or equal to 60", unlike every other table."""
    with pytest.raises(ConfigError) as refused:
        ros2_config({"command_timeout_s": value})
    assert "ros2.command_timeout_s: Input should be a finite number" in str(refused.value)


def test_names_of_their_own_and_bases_sharing_an_absolute_tf_are_taken() -> None:
    two = [BASE, {**BASE, "name": "other", "left": "wl2", "right": "wr2"}]
    assert ros2_config({}, [BASE]).ros2 is not None
    assert ros2_config({"namespace": "/robot"}, two).ros2.tf == "/tf"  # both bases' /tf
    assert ros2_config({"odom": "/diagnostics"}).ros2 is not None  # no base: no odom topic


def test_the_reset_service_names_the_devices_another_clients_claim_kept_e_stopped() -> None:
    _, bridge, face = gripper_face()
    assert face._reset_estop({}).result(1) == {"success": True, "message": "every bus reset"}
    bridge.kept = ["la1", "la2"]
    assert face._reset_estop({}).result(1) == {
        "success": True,
        "message": "every bus reset; not reset, claimed by another client: la1, la2"}
