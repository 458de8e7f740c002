"""The ROS 2 face end to end, against an independent implementation of rmw_zenoh's format:
ROBOTIS's ``zenoh-ros2-sdk`` (which decodes with ``rosbags``) subscribes to the gateway's joint
states, diagnostics and e-stop state, publishes commands and trajectories, calls its services
and lists its topics; the simulators' wire records say what reached the devices.

One daemon (``serve`` on a thread, zenoh on 127.0.0.1 only, no multicast) serves every test.
The SDK would clone message definitions with git: it is given a directory made at test time
from rosbags' ROS 2 Jazzy definitions, so nothing reaches the network."""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from pathlib import Path

import can
import numpy
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.ros2 import messages, rmw_zenoh
from busgate.codecs.zlac706_common import rpm_from_speed_raw
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port
from tests.test_zenoh_api import Daemon, connected, get
from tests.wire_frames import received, tick_targets, written_speed

TURN = 2 * math.pi
NODE = "busgate_gw1"
#: la1: 5 µm a count, 1–8 mm, at most 10 mm/s (at 20 ms, 40 counts a tick).
GRIPPER = {"name": "gripper", "unit": "m", "scale": 5e-6, "min": 0.001, "max": 0.008,
           "max_velocity": 0.01}
#: the wheel: a velocity joint, at most 2 turns a second, 8 turns a second².
WHEEL = {"name": "wheel", "unit": "rad", "scale": TURN / 10_000, "max_velocity": 2 * TURN,
         "max_acceleration": 8 * TURN}
#: a base's wheels: 10000 pulses a turn, at most 2 turns a second.
BASE_WHEEL = {"unit": "rad", "scale": TURN / 10_000, "max_velocity": 2 * TURN}
MESSAGE_TYPES = [
    "builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration", "std_msgs/msg/Header",
    "std_msgs/msg/Bool", "sensor_msgs/msg/JointState", "trajectory_msgs/msg/JointTrajectory",
    "trajectory_msgs/msg/JointTrajectoryPoint", "diagnostic_msgs/msg/DiagnosticArray",
    "diagnostic_msgs/msg/DiagnosticStatus", "diagnostic_msgs/msg/KeyValue",
    "service_msgs/msg/ServiceEventInfo", "geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3",
    "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/TwistWithCovariance", "tf2_msgs/msg/TFMessage",
    "geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/Transform",
]
#: std_srvs/srv/Trigger as ROS 2 defines it (rosbags has no service types).
TRIGGER_SRV = "---\nbool success\nstring message\n"
_channels = itertools.count()
#: What ROS 2 publishes as the type hash of sensor_msgs/msg/JointState (rosidl, Jazzy).
JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"


def messages_dir(root: Path) -> Path:
    """A messages directory for the SDK: each type's own definition, from rosbags' Jazzy
    store (``generate_msgdef``'s first section; the rest are its dependencies)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name in MESSAGE_TYPES:
        package, _, message = name.split("/")
        text = store.generate_msgdef(name, ros_version=2)[0].split("\n" + "=" * 80)[0]
        path = root / package / "msg" / f"{message}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
    (root / "std_srvs" / "srv").mkdir(parents=True)
    (root / "std_srvs" / "srv" / "Trigger.srv").write_text(TRIGGER_SRV)
    return root


class Received:
    """What an SDK subscriber got, for waiting on."""

    def __init__(self) -> None:
        self.messages: list = []
        self.changed = threading.Condition()

    def __call__(self, message) -> None:
        with self.changed:
            self.messages.append(message)
            self.changed.notify_all()

    def wait(self, predicate, timeout: float = 10.0):
        """The first message (from now on) ``predicate`` holds for."""
        with self.changed:
            start = len(self.messages)
            deadline = time.monotonic() + timeout
            while True:
                for message in self.messages[start:]:
                    if predicate(message):
                        return message
                start = len(self.messages)
                left = deadline - time.monotonic()
                assert left > 0, "no such message came"
                self.changed.wait(left)


#: The odometry's covariance diagonals: diff_drive_controller's suggested start, as a user
#: would set them.
POSE_VARIANCES = [0.001, 0.001, 0.001, 0.001, 0.001, 0.01]
TWIST_VARIANCES = [0.002, 0.002, 0.002, 0.002, 0.002, 0.03]


@pytest.fixture(scope="module")
def ros(tmp_path_factory):
    """The daemon with ``[ros2]``, its simulators, a plain zenoh client, and the SDK set up
    to reach it."""
    sdk = pytest.importorskip("zenoh_ros2_sdk")
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    port = unused_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    la_sim = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    channel = f"test-ros2-{next(_channels)}"
    can_sim = CanSimulator(zcan, [Zlac706CanDevice(5, heartbeat_ms=50),
                                  Zlac706CanDevice(6, heartbeat_ms=20),
                                  Zlac706CanDevice(7, heartbeat_ms=20)],
                           bus=can.Bus(interface="virtual", channel=channel))
    for simulator in (la_sim, can_sim):
        simulator.start()
    daemon = Daemon({
        "gateway": {"name": "gw1"},
        "zenoh": {"listen": [endpoint]},
        "ros2": {"pose_covariance_diagonal": POSE_VARIANCES,
                 "twist_covariance_diagonal": TWIST_VARIANCES},
        "buses": [
            {"name": "uart0", "transport": "serial", "port": la_sim.port, "baudrate": 921_600,
             "reply_margin_ms": 50, "devices": [
                 {"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 50, "joint": GRIPPER},
                 {"name": "la2", "kind": "inspire_la", "id": 2, "poll_hz": 50}]},
            {"name": "can0", "transport": "can", "interface": "virtual", "channel": channel,
             "reply_margin_ms": 50, "devices": [
                 {"name": "drive", "kind": "zlac706", "id": 5, "heartbeat_ms": 50,
                  "joint": WHEEL},
                 {"name": "wl", "kind": "zlac706", "id": 6, "heartbeat_ms": 20,
                  "joint": BASE_WHEEL | {"name": "left_wheel"}},
                 {"name": "wr", "kind": "zlac706", "id": 7, "heartbeat_ms": 20,
                  "joint": BASE_WHEEL | {"name": "right_wheel", "scale": -TURN / 10_000}}]}],
        "bases": [{"name": "base", "left": "wl", "right": "wr", "wheel_radius_m": 0.1,
                   "track_m": 0.4, "max_linear_mps": 1.0, "max_angular_radps": 2.0,
                   "max_linear_accel": 2.0, "max_angular_accel": 6.0}],
    })
    client = connected(zenoh.open(session_config(mode="peer", connect=[endpoint])))
    message_registry._registry = None
    message_registry.get_registry(str(messages_dir(tmp_path_factory.mktemp("msgs"))))
    ZenohSession._instance = None
    session = ZenohSession.get_instance("127.0.0.1", port)
    world = {"sdk": sdk, "port": port, "client": client, "la": la_sim, "can": can_sim,
             "entities": [], "types": session.store.types}
    yield world
    for entity in world["entities"]:
        entity.close()
    session.session.close()
    ZenohSession._instance = None
    message_registry._registry = None
    client.close()
    daemon.shutdown()
    for simulator in (la_sim, can_sim):
        simulator.stop()


def subscribe(ros, topic: str, type_name: str) -> Received:
    got = Received()
    ros["entities"].append(ros["sdk"].ROS2Subscriber(
        topic, type_name, got, router_ip="127.0.0.1", router_port=ros["port"]))
    return got


def publisher(ros, topic: str, type_name: str, qos: str | None = None):
    made = ros["sdk"].ROS2Publisher(topic, type_name, router_ip="127.0.0.1",
                                    router_port=ros["port"], qos=qos)
    ros["entities"].append(made)
    time.sleep(0.3)  # the gateway's subscription learns of it before its first sample
    return made


def service(ros, name: str):
    # The SDK refuses an empty request definition; rosidl gives an empty request this one
    # field (and hashes it so), which is what the SDK is told here.
    made = ros["sdk"].ROS2ServiceClient(
        name, "std_srvs/srv/Trigger", router_ip="127.0.0.1", router_port=ros["port"],
        timeout=10.0, request_definition="uint8 structure_needs_at_least_one_member",
        response_definition="bool success\nstring message")
    ros["entities"].append(made)
    return made


def header(ros):
    types = ros["types"]
    return types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](0, 0), "")


def joint_state(ros, names: list[str], **values: list[float]) -> dict:
    """A JointState's fields for the SDK's publisher (rosbags takes float arrays as numpy)."""
    return {"header": header(ros), "name": names} | {
        field: numpy.array(values.get(field, []), dtype=numpy.float64)
        for field in ("position", "velocity", "effort")}


def command(ros, device: str, payload: dict) -> dict:
    [reply] = get(ros["client"], f"busgate/gw1/dev/{device}/cmd", json.dumps(payload))
    return reply


def la_targets(ros, since: int, device_id: int) -> list[int]:
    """Every follow target the LA bus received for ``device_id`` after its ``since``-th frame."""
    return [targets[device_id] for _, frame in received(ros["la"], since, la)
            if (targets := tick_targets(frame)) and device_id in targets]


def wait_for_target(ros, since: int, device_id: int, target: int) -> list[int]:
    deadline = time.monotonic() + 10
    while (targets := la_targets(ros, since, device_id))[-1:] != [target]:
        assert time.monotonic() < deadline, f"no ramp to {target}: {targets[-5:]}"
        time.sleep(0.02)
    return targets


def test_joint_states_reach_a_ros_subscriber_in_si_with_nan_where_unknown(ros) -> None:
    states = subscribe(ros, "/robot_joint_states", "sensor_msgs/msg/JointState")
    message = states.wait(lambda m: list(m.name) == ["gripper", "la2", "wheel", "left_wheel",
                                                     "right_wheel"])
    assert math.isnan(message.velocity[0])  # an LA reports no velocity
    position_raw = next(d for d in get(ros["client"], "busgate/gw1/info", "")[0]["buses"][0]
                    ["devices"] if d["name"] == "la1")["state"]["position"]
    assert message.position[0] == pytest.approx(position_raw * 5e-6, abs=0.0005)
    assert message.header.stamp.sec > 1_700_000_000  # when the values were read


def test_the_node_its_topics_and_services_are_listed(ros) -> None:
    discovery = ros["sdk"]
    topics = dict(discovery.get_topic_names_and_types(domain_id=0, router_ip="127.0.0.1",
                                                      router_port=ros["port"], timeout=2.0))
    assert topics["/robot_joint_states"] == ["sensor_msgs/msg/JointState"]
    assert topics["/robot_joint_commands"] == ["sensor_msgs/msg/JointState"]
    assert topics["/joint_trajectory"] == ["trajectory_msgs/msg/JointTrajectory"]
    assert topics["/diagnostics"] == ["diagnostic_msgs/msg/DiagnosticArray"]
    assert topics[f"/{NODE}/estopped"] == ["std_msgs/msg/Bool"]
    services = dict(discovery.get_service_names_and_types(domain_id=0, router_ip="127.0.0.1",
                                                          router_port=ros["port"], timeout=2.0))
    assert services[f"/{NODE}/estop"] == services[f"/{NODE}/reset_estop"] == [
        "std_srvs/srv/Trigger"]
    info = discovery.get_topic_info("/robot_joint_states", domain_id=0, router_ip="127.0.0.1",
                                    router_port=ros["port"], timeout=2.0, verbose=True)
    [ours] = [p for p in info.publishers if p.node_name == NODE]
    assert (ours.topic_type, ours.type_hash) == ("sensor_msgs/msg/JointState", JOINT_STATE_HASH)
    assert ours.qos == "2::,5:,:,:,,"  # sensor data: best effort, keep last 5


def test_a_position_command_ramps_within_the_limits_and_is_held(ros) -> None:
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState",
                         qos="::,1:,:,:,,")
    since = len(ros["la"].recorder.received())
    commands.publish(**joint_state(ros, ["gripper"], position=[0.004]))
    targets = wait_for_target(ros, since, 1, 800)
    steps = [abs(b - a) for a, b in itertools.pairwise(targets)]
    assert max(steps) <= 40  # 10 mm/s at 20 ms: 40 counts a tick
    time.sleep(0.5)  # silence: the joint stays where it was sent, no stop
    assert command(ros, "la1", {"op": "status"})["state"]["target"] == 800
    since = len(ros["la"].recorder.received())
    commands.publish(**joint_state(ros, ["gripper"], position=[0.5]))  # past max
    targets = wait_for_target(ros, since, 1, 1600)  # 8 mm: clamped to the limit
    assert max(targets) == 1600


#: The attachment's source GID of the commands the tests put as a ROS publisher.
PUBLISHER_GID = rmw_zenoh.new_gid()
_sequence = itertools.count(1)


def rmw_put(ros, key: str, payload: bytes, *, attached: bool = True) -> None:
    """A put as rmw_zenoh's publishers make it: with its attachment, unless not ``attached``."""
    attachment = rmw_zenoh.attachment(next(_sequence), time.time_ns(), PUBLISHER_GID)
    ros["client"].put(key, payload, attachment=attachment if attached else None)


COMMANDS_KEY = rmw_zenoh.data_key(
    0, "/robot_joint_commands", "sensor_msgs/msg/JointState", "jazzy")


@pytest.mark.parametrize(("wildcard", "attached"), [
    ("0/robot_joint_commands/**", True), ("*/robot_joint_commands/*/*", True),
    (COMMANDS_KEY, False)])
def test_a_command_put_on_a_wildcard_key_or_unattached_moves_nothing(
        ros, wildcard, attached) -> None:
    """rmw_zenoh's publishers put on their topic's exact key, with their attachment. A
    well-formed JointState put on a wildcard key (any peer's) reaches the gateway's
    subscription too, and must move nothing: only the exact key commands (as only a device's
    own ``cmd`` leaf does on the zenoh API). One put without the attachment, which rmw_zenoh's
    subscriptions drop, moves nothing either: a plain zenoh put is not a ROS command."""
    key = COMMANDS_KEY

    def gripper_at(position: float) -> bytes:
        return messages.encode("sensor_msgs/msg/JointState", {
            "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
            "name": ["gripper"], "position": [position], "velocity": [], "effort": []})

    since = len(ros["la"].recorder.received())
    rmw_put(ros, key, gripper_at(0.003))
    wait_for_target(ros, since, 1, 600)  # the exact key commands
    since = len(ros["la"].recorder.received())
    rmw_put(ros, wildcard, gripper_at(0.007), attached=attached)
    time.sleep(0.5)  # a stream toward 1400 would have ticked 25 times
    assert la_targets(ros, since, 1) == []


def test_a_command_over_64_kib_is_dropped_before_it_is_decoded(ros) -> None:
    """A peer's 16 MB JointState was decoded whole, and each of its names ramped in turn."""
    key = rmw_zenoh.data_key(0, "/robot_joint_commands", "sensor_msgs/msg/JointState", "jazzy")

    def gripper_among_others(position: float, others: int) -> bytes:
        names = ["gripper", *(f"other{n:094d}" for n in range(others))]
        return messages.encode("sensor_msgs/msg/JointState", {
            "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
            "name": names, "position": [position] + [math.nan] * others, "velocity": [],
            "effort": []})

    under, over = gripper_among_others(0.002, 500), gripper_among_others(0.006, 700)
    assert len(under) < 64 * 1024 < len(over)
    since = len(ros["la"].recorder.received())
    rmw_put(ros, key, under)
    wait_for_target(ros, since, 1, 400)
    since = len(ros["la"].recorder.received())
    rmw_put(ros, key, over)
    time.sleep(0.5)  # a stream toward 1200 would have ticked 25 times
    assert la_targets(ros, since, 1) == []


def test_a_sample_the_node_drops_is_told_in_the_diagnostics(ros) -> None:
    """The node counted what it dropped but no ROS user could see it: a publisher of the
    wrong type or a bad serializer learned nothing from /diagnostics."""
    diagnostics = subscribe(ros, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    rmw_put(ros, COMMANDS_KEY, b"\x00\x01\x00\x00 not a JointState")

    def input_status(array):
        return next(s for s in array.status if s.name == f"{NODE}: input")

    reason = "the last a sample that is not sensor_msgs/msg/JointState CDR"
    told = input_status(diagnostics.wait(lambda a: reason in input_status(a).message))
    assert told.level == 1  # WARN, while it comes
    assert told.message.startswith("dropped in the last second: robot_joint_commands: ")
    values = {kv.key: kv.value for kv in told.values}
    assert values["dropped on robot_joint_commands"].endswith(f", {reason}")
    assert int(values["dropped"]) >= 1


def test_a_service_asked_on_a_wildcard_key_is_not_answered(ros) -> None:
    """The reset's request on its exact key without rmw_zenoh's attachment gets an error reply;
    on a wildcard key it is dropped before that: nothing is done and nothing answers."""
    exact = rmw_zenoh.data_key(0, f"/{NODE}/reset_estop", "std_srvs/srv/Trigger", "jazzy")
    [refused] = list(ros["client"].get(exact, payload=b"", timeout=2))
    assert refused.err is not None
    assert list(ros["client"].get(f"0/{NODE}/reset_estop/**", payload=b"", timeout=1)) == []


def test_a_command_for_a_joint_another_client_holds_moves_nothing(ros) -> None:
    assert command(ros, "la2", {"op": "claim", "client": "teleop", "ttl_s": 30})["ok"]
    diagnostics = subscribe(ros, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState")
    try:
        since = len(ros["la"].recorder.received())
        commands.publish(**joint_state(ros, ["la2", "elbow"], position=[1500.0, 1.0]))

        def la2_status(array):
            return next((s for s in array.status if s.name == f"{NODE}: joint la2"), None)

        told = diagnostics.wait(lambda a: la2_status(a) is not None
                                and la2_status(a).level == 1)
        values = {kv.key: kv.value for kv in la2_status(told).values}
        assert values["claimed_by"] == "teleop" and "teleop" in values["last_refusal"]
        [commands_status] = [s for s in told.status if s.name == f"{NODE}: commands"]
        assert commands_status.level == 1 and "elbow" in commands_status.message
        assert la_targets(ros, since, 2) == []
    finally:
        assert command(ros, "la2", {"op": "release", "client": "teleop"})["ok"]


@pytest.mark.parametrize(("names", "more", "velocity", "refusal"), [
    # ros2_control's topic-based system, the gripper state-only and a typo with its interface
    (["gripper", "gripper_x"], [], [],
     "position has 1, velocity 0 values for 2 names, 1 of them no joint of this gateway"),
    (["gripper_x", "gripper"], [], [0.5],
     "position has 1, velocity 1 values for 2 names, 1 of them no joint of this gateway"),
    # the wheel commanded through an interface it does not have
    (["gripper", "wheel"], [1.0], [], "position given for velocity joint wheel"),
])
def test_a_command_that_cannot_say_whose_each_value_is_moves_nothing(
        ros, names, more, velocity, refusal) -> None:
    """The gripper took a value by its place in the list, meant for another name, or moved
    while the wheel's value was thrown away without a word: the message is refused whole,
    shown in the gripper's diagnostics. A command for la2 sent after it, seen on the wire,
    says the gateway took the refused one before it."""
    gripper_at = command(ros, "la1", {"op": "status"})["state"]["target"]
    position = [0.006 if gripper_at != 1200 else 0.005, *more]  # somewhere the gripper is not
    la2_at = command(ros, "la2", {"op": "status"})["state"]["target"]
    la2_next = 300 if la2_at != 300 else 500
    diagnostics = subscribe(ros, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState")
    since = len(ros["la"].recorder.received())
    commands.publish(**joint_state(ros, names, position=position, velocity=velocity))
    commands.publish(**joint_state(ros, ["la2"], position=[float(la2_next)]))
    wait_for_target(ros, since, 2, la2_next)
    assert la_targets(ros, since, 1) == []

    def gripper_refusal(array) -> str:
        [status] = [s for s in array.status if s.name == f"{NODE}: joint gripper"]
        return {kv.key: kv.value for kv in status.values}["last_refusal"]

    diagnostics.wait(lambda a: refusal in gripper_refusal(a))


def commands_values(array) -> dict[str, str]:
    [status] = [s for s in array.status if s.name == f"{NODE}: commands"]
    return {kv.key: kv.value for kv in status.values}


def test_values_without_names_move_nothing_and_are_shown_in_the_commands_status(
        ros, caplog) -> None:
    """A message of values without names was refused in silence: no line, no diagnostics,
    ``<node>: input`` ok."""
    diagnostics = subscribe(ros, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState")
    since = len(ros["la"].recorder.received())
    commands.publish(**joint_state(ros, [], position=[0.003], velocity=[1.0]))
    why = "position has 1, velocity 1 values for no names (name their joints)"
    told = diagnostics.wait(lambda a: why in commands_values(a).get("last_refusal", ""))
    [status] = [s for s in told.status if s.name == f"{NODE}: commands"]
    assert status.level == 1 and why in status.message
    assert any(r.getMessage().startswith("ros2: a command naming no joint of this gateway "
                                         "refused, nothing in it moves: whose is each value?")
               for r in caplog.records)
    assert la_targets(ros, since, 1) == []


def test_a_silent_velocity_joint_ramps_to_zero_after_the_timeout(ros) -> None:
    assert command(ros, "drive", {"op": "set_mode", "mode": "velocity"})["ok"]
    assert command(ros, "drive", {"op": "enable"})["ok"]
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState")
    since = len(ros["can"].recorder.received())
    commands.publish(**joint_state(ros, ["wheel"], velocity=[TURN]))  # 60 rpm
    sent = time.monotonic()

    def speeds() -> list[tuple[float, float]]:
        return [(record.start, rpm_from_speed_raw(speed))
                for record, frame in received(ros["can"], since, zcan)
                if (speed := written_speed(frame)) is not None]

    deadline = time.monotonic() + 10
    while not any(rpm > 59 for _, rpm in speeds()) or speeds()[-1][1] != 0:  # 60 rpm, raw
        assert time.monotonic() < deadline, f"no ramp up and down: {speeds()[-5:]}"
        time.sleep(0.02)
    written = speeds()
    top = next(i for i, (_, rpm) in enumerate(written) if rpm > 59)
    held = written[top][1]
    first_lower = next(t for t, rpm in written[top:] if rpm < held)
    # The ramp down starts after the timeout, timed from when the command was taken: the
    # first write followed that by a hand-over to the bus thread and its tick, as the first
    # lower one follows the timeout (so at most a period apart either way). It goes down at
    # 8 turns/s²: 9.6 rpm a 20 ms tick.
    assert first_lower - written[0][0] >= 0.5 - 0.02
    down = list(dict.fromkeys(rpm for _, rpm in written[top:]))
    assert down[-1] == 0 and len(down) >= 6, down
    assert all(0 < a - b <= 9.6 + 0.4 for a, b in itertools.pairwise(down)), down
    assert time.monotonic() - sent < 10
    assert command(ros, "drive", {"op": "disable"})["ok"]


def test_a_trajectory_is_played_and_an_empty_one_cancels_it(ros, caplog) -> None:
    # A trajectory starts from where the joint is: within its limits (a simulator starts at
    # 0), brought there by a ROS command (the face holds the joint for its client a while)
    commands = publisher(ros, "/robot_joint_commands", "sensor_msgs/msg/JointState")
    since = len(ros["la"].recorder.received())
    commands.publish(**joint_state(ros, ["gripper"], position=[0.003]))
    wait_for_target(ros, since, 1, 600)
    trajectories = publisher(ros, "/joint_trajectory", "trajectory_msgs/msg/JointTrajectory")
    since = len(ros["la"].recorder.received())
    types = ros["types"]

    def point(position: float, seconds: float):
        empty = numpy.array([], dtype=numpy.float64)
        whole, fraction = divmod(seconds, 1)
        duration = types["builtin_interfaces/msg/Duration"](int(whole), round(fraction * 1e9))
        return types["trajectory_msgs/msg/JointTrajectoryPoint"](
            numpy.array([position]), empty, empty, empty, duration)

    trajectories.publish(header=header(ros), joint_names=["gripper"], points=[point(0.002, 0.4)])
    wait_for_target(ros, since, 1, 400)
    trajectories.publish(header=header(ros), joint_names=["gripper"], points=[point(0.007, 30)])
    deadline = time.monotonic() + 10
    while not get(ros["client"], "busgate/gw1/trajectory", '{"op":"status"}')[0]["trajectories"]:
        assert time.monotonic() < deadline, "the trajectory does not play"
        time.sleep(0.05)
    trajectories.publish(header=header(ros), joint_names=[], points=[])
    while get(ros["client"], "busgate/gw1/trajectory", '{"op":"status"}')[0]["trajectories"]:
        assert time.monotonic() < deadline, "the empty trajectory did not cancel it"
        time.sleep(0.05)
    # The controller stops so whether or not anything plays: nothing was refused.
    caplog.clear()
    since = len(ros["la"].recorder.received())
    trajectories.publish(header=header(ros), joint_names=["gripper"], points=[])
    trajectories.publish(header=header(ros), joint_names=["gripper"], points=[point(0.002, 0.4)])
    wait_for_target(ros, since, 1, 400)  # the play behind it was sent once it was answered
    assert not [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]


def test_every_trajectory_naming_a_joint_the_gateway_lacks_is_told_refused(ros, caplog) -> None:
    """A trajectory with a misspelt joint was told only as an unknown name, the first time,
    and its refusal thrown away."""
    diagnostics = subscribe(ros, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    trajectories = publisher(ros, "/joint_trajectory", "trajectory_msgs/msg/JointTrajectory")
    types = ros["types"]
    point = types["trajectory_msgs/msg/JointTrajectoryPoint"](
        numpy.array([0.002]), *[numpy.array([], dtype=numpy.float64)] * 3,
        types["builtin_interfaces/msg/Duration"](1, 0))
    why = "no joint 'typo_joint' on this gateway"
    line = f"ros2: a trajectory refused, it plays nothing: {why}"
    deadline = time.monotonic() + 10
    told: list[str] = []
    while not told:  # one told in the second before this test may hold its line back
        assert time.monotonic() < deadline, "no refusal told"
        trajectories.publish(header=header(ros), joint_names=["typo_joint"], points=[point])
        time.sleep(0.5)
        told = [r.getMessage() for r in caplog.records if r.getMessage().startswith(line)]
    assert len(told) == 1
    diagnostics.wait(lambda a: commands_values(a).get("last_refusal") == f"trajectory: {why}")
    caplog.clear()
    for _ in range(2):  # again: told again, once a second at most
        time.sleep(0.6)
        trajectories.publish(header=header(ros), joint_names=["typo_joint"], points=[point])
    deadline = time.monotonic() + 10
    while not [r for r in caplog.records if r.getMessage().startswith(line)]:
        assert time.monotonic() < deadline, "a repeated refusal was not told"
        time.sleep(0.05)


def test_trajectory_messages_are_carried_out_in_order_the_newest_of_a_burst_last(ros) -> None:
    """An empty trajectory right behind a play went to the trajectory key's control lane and
    found nothing running yet: the play then ran to its end. Of a burst, the fifth and later
    were refused busy while older ones played."""
    trajectories = publisher(ros, "/joint_trajectory", "trajectory_msgs/msg/JointTrajectory")
    types = ros["types"]

    def played(seconds: int):
        empty = numpy.array([], dtype=numpy.float64)
        duration = types["builtin_interfaces/msg/Duration"](seconds, 0)
        point = types["trajectory_msgs/msg/JointTrajectoryPoint"](
            numpy.array([0.004]), empty, empty, empty, duration)
        return {"header": header(ros), "joint_names": ["gripper"], "points": [point]}

    def lengths() -> list[int]:  # of the trajectories running, in s
        running = get(ros["client"], "busgate/gw1/trajectory", '{"op":"status"}')[0]
        return [round(t["end_at"] - t["start_at"]) for t in running["trajectories"]]

    def comes_to(expected: list[int]) -> None:
        deadline = time.monotonic() + 10
        while lengths() != expected:
            assert time.monotonic() < deadline, lengths()
            time.sleep(0.05)
        time.sleep(1.0)  # and stays so: nothing older starts after it
        assert lengths() == expected

    trajectories.publish(**played(30))
    trajectories.publish(header=header(ros), joint_names=[], points=[])
    comes_to([])
    for seconds in range(30, 38):
        trajectories.publish(**played(seconds))
    comes_to([37])
    trajectories.publish(header=header(ros), joint_names=[], points=[])
    comes_to([])


def test_the_estop_service_stops_every_bus_and_the_reset_brings_them_back(ros) -> None:
    estopped = subscribe(ros, f"/{NODE}/estopped", "std_msgs/msg/Bool")
    estopped.wait(lambda m: m.data is False)
    response = service(ros, f"/{NODE}/estop").call()
    assert response.success is True
    estopped.wait(lambda m: m.data is True, timeout=3)
    info = get(ros["client"], "busgate/gw1/info", "")[0]
    assert all(d["state"]["estopped"] for bus in info["buses"] for d in bus["devices"])
    response = service(ros, f"/{NODE}/reset_estop").call()
    assert response.success is True, response.message
    estopped.wait(lambda m: m.data is False, timeout=3)


def test_a_base_drives_from_the_zenoh_api_and_its_odometry_is_published(ros) -> None:
    client = ros["client"]
    odometry: list[dict] = []
    told = client.declare_subscriber(
        "busgate/gw1/base/base/odom",
        lambda sample: odometry.append(json.loads(sample.payload.to_bytes())))
    events: list[dict] = []
    heard = client.declare_subscriber(
        "busgate/gw1/events", lambda sample: events.append(json.loads(sample.payload.to_bytes())))
    try:
        [reply] = get(client, "busgate/gw1/base/base/cmd", '{"op":"enable"}')
        assert reply["ok"], reply
        [reply] = get(client, "busgate/gw1/base/base/cmd", '{"op":"reset_odometry"}')
        since = len(ros["can"].recorder.received())
        [reply] = get(client, "busgate/gw1/base/base/cmd",
                      '{"op":"twist","linear":0.3,"duration_s":0.6}')
        assert reply["ok"] and reply["base"]["target"] == {"linear": 0.3, "angular": 0.0}
        deadline = time.monotonic() + 10
        while not odometry or odometry[-1]["x"] < 0.1:
            assert time.monotonic() < deadline, odometry[-1:]
            time.sleep(0.05)
        nodes = {frame.device_id for _, frame in received(ros["can"], since, zcan)
                 if written_speed(frame)}
        assert nodes == {6, 7}
        client.put("busgate/gw1/base/base/twist", '{"linear": "fast"}')  # refused, an event
        [reply] = get(client, "busgate/gw1/base/ghost/cmd", '{"op":"stop"}')
        assert reply["error"]["code"] == "unknown_device"
        deadline = time.monotonic() + 5
        while not (refused := [e for e in events if e.get("type") == "command_refused"]):
            assert time.monotonic() < deadline, events
            time.sleep(0.05)
        assert (refused[0]["device"], refused[0]["code"]) == ("base", "bad_command")
    finally:
        heard.undeclare()
        told.undeclare()
        get(client, "busgate/gw1/base/base/cmd", '{"op":"stop"}')


def test_cmd_vel_drives_the_base_and_odom_and_tf_follow(ros) -> None:
    odom = subscribe(ros, "/odom", "nav_msgs/msg/Odometry")
    tf = subscribe(ros, "/tf", "tf2_msgs/msg/TFMessage")
    [reply] = get(ros["client"], "busgate/gw1/base/base/cmd", '{"op":"enable"}')
    assert reply["ok"]
    start = odom.wait(lambda m: True)
    twist = publisher(ros, "/cmd_vel", "geometry_msgs/msg/Twist")
    types = ros["types"]
    vector = types["geometry_msgs/msg/Vector3"]
    for _ in range(10):  # a controller's stream: 0.2 rad/s on the spot
        twist.publish(linear=vector(0.0, 0.0, 0.0), angular=vector(0.0, 0.0, 0.2))
        time.sleep(0.05)
    turned = odom.wait(lambda m: m.pose.pose.orientation.z > start.pose.pose.orientation.z
                       + 0.01)
    assert turned.header.frame_id == "odom" and turned.child_frame_id == "base_link"
    for matrix, variances in ((turned.pose.covariance, POSE_VARIANCES),
                              (turned.twist.covariance, TWIST_VARIANCES)):
        assert list(matrix[::7]) == variances  # the diagonal, as configured
        assert [v for i, v in enumerate(matrix) if i % 7] == [0.0] * 30  # and nothing else
    assert abs(turned.pose.pose.position.x - start.pose.pose.position.x) < 0.01
    [transform] = tf.wait(lambda m: True).transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("odom", "base_link")
