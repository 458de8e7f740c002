"""The SDK's joints (``Device.joint``, ``Client.joint``, ``Client.joints``,
``Client.joints_feed``) on both faces, against real gateways over real zenoh sessions: a
gateway of this module (``gwj``: ``busgate run`` on an Inspire LA simulator, ``la1`` a joint
``lift`` calibrated in metres with limits, ``la2`` without a joint table) and the shared demo
(``wheel``, a ZLAC706 on CAN, a velocity joint); and the pieces without a gateway
(finding a device by its joint's name, a joint ``info`` does not describe, a joints message
that is not one).

One gateway process for the module besides the shared demo; each test connects clients of its
own. Commands that must go through are sent ``patiently`` (``tests.sdk_helpers``).
"""

from __future__ import annotations

import asyncio
import inspect
import json
import logging
import math
import threading
import time

import pytest
from pydantic import ValidationError

import busgate.client as bc
from busgate.client.base import Found, locate
from busgate.client.joints import follow_field
from busgate.client.messages import joints_message
from busgate.codecs import inspire_la
from busgate.errors import CommandError
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from tests.conftest import unused_loopback_port
from tests.gateway_process import GatewayProcess, bus_table, write_config
from tests.sdk_helpers import EventWatch, patiently, patiently_async, the_client_id
from tests.test_client_faces import TWINS, function_of, kind, public

#: ``la1`` as the joint ``lift``: 10 µm a raw unit, from 0 at raw 0, held within 2–18 mm.
SCALE, LOW, HIGH = 1e-5, 0.002, 0.018
#: Hang guards, not speed requirements.
DEADLINE_S = 10.0


@pytest.fixture(scope="module")
def gwj(tmp_path_factory):
    """``busgate run`` as gateway ``gwj`` on an Inspire LA simulator: its endpoint."""
    endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    with SerialSimulator(inspire_la, [InspireLaDevice(1), InspireLaDevice(2)],
                         baudrate=921_600) as simulator:
        bus = bus_table("uart0", simulator.port, 921_600,
                        {"la1": ("inspire_la", 1), "la2": ("inspire_la", 2)})
        bus = bus.replace('id = 1\n', f'id = 1\n[buses.devices.joint]\nname = "lift"\n'
                          f'unit = "m"\nscale = {SCALE}\nmin = {LOW}\nmax = {HIGH}\n', 1)
        config = write_config(tmp_path_factory.mktemp("gwj") / "gwj.toml", endpoint, bus,
                              name="gwj")
        gateway = GatewayProcess(config)
        try:
            gateway.wait_for(" serving ")
            yield endpoint
        finally:
            assert gateway.stop() == 0, gateway.lines


@pytest.fixture
def connect(request):
    """``connect(endpoint, suffix)``: a client (id from the test's name), closed after it."""
    clients: list[bc.Client] = []

    def open_client(endpoint: str, suffix: str = "") -> bc.Client:
        name = f"{request.node.name}-{suffix}" if suffix else request.node.name
        clients.append(bc.connect(endpoint, client_id=the_client_id(name)))
        return clients[-1]

    yield open_client
    for client in clients:
        client.close()


def until(condition, timeout: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.02)


def near(value: float | None, expected: float) -> bool:
    return value is not None and abs(value - expected) <= SCALE / 2 + 1e-12


# -- finding and describing ------------------------------------------------------------------


def test_a_joints_name_finds_its_device_and_info_describes_the_joint(gwj, connect) -> None:
    client = connect(gwj)
    lift = client.joint("lift")
    assert isinstance(lift, bc.Joint) and lift.device.name == "la1"
    assert (lift.name, lift.type, lift.unit) == ("lift", "position", "m")
    assert isinstance(lift.info, bc.JointInfo) and lift.info.configured
    assert (lift.info.scale, lift.info.min, lift.info.max) == (SCALE, LOW, HIGH)
    assert repr(lift) == "<Joint gwj/lift (position, m)>"
    assert client.device("gwj/lift").name == "la1"  # a joint's name is a device's name too
    assert client.joint("la1").name == "lift" and client.device("la1").joint.name == "lift"
    raw = client.device("la2").joint
    assert (raw.name, raw.type, raw.unit, raw.info.configured) == ("la2", "position", "raw", False)
    with pytest.raises(bc.UnknownDeviceError, match="'elbow'"):
        client.joint("elbow")
    joints = {d.name: d.joint for d in client.devices()}
    assert joints["la1"].name == "lift" and joints["la2"].unit == "raw"


# -- moves, states, limits -------------------------------------------------------------------


def test_a_joint_moves_in_si_and_reads_back_in_si(gwj, connect) -> None:
    lift = connect(gwj).joint("lift")
    patiently(lift.device.enable)
    for goal in (0.0123, 0.004):
        reply = patiently(lift.move, goal)
        assert reply["ok"] is True and reply["state"]["target"] == round(goal / SCALE)
        assert reply["joint"]["name"] == "lift" and reply["joint"]["unit"] == "m"
        until(lambda goal=goal: near(lift.state().position, goal))
    state = lift.state()
    assert isinstance(state, bc.JointState)
    assert (state.name, state.unit, state.velocity) == ("lift", "m", None)
    assert state.effort is not None  # the force sensor's reading, in N


def test_a_move_beyond_a_limit_is_refused_naming_the_joint_limit_and_value(gwj, connect) -> None:
    lift = connect(gwj).joint("lift")
    with pytest.raises(bc.OutOfRangeError, match=r"joint lift: position 0\.5 m .*max 0\.018 m"):
        lift.move(0.5)
    with pytest.raises(bc.OutOfRangeError, match="min"):
        lift.move(0.001)
    with pytest.raises(bc.BadCommandError):
        lift.set_velocity(0.01)  # a position joint takes no velocity


def test_a_joint_follow_stream_is_held_within_the_limits_and_says_so_once(gwj, connect) -> None:
    client = connect(gwj)
    lift = client.joint("lift")
    patiently(lift.device.enable)
    with EventWatch(gwj, "gwj") as events:
        since = time.monotonic()
        with lift.device.claim(ttl_s=2.0), lift.follow() as stream:
            assert isinstance(stream, bc.JointFollow) and stream.field == "joint"
            for step in range(40):
                stream.set(0.01 + step * 0.001)  # past max from the ninth on
                time.sleep(0.02)

            def at_the_limit() -> bool:  # the stream kept fresh while the actuator gets there
                stream.set(0.049)
                time.sleep(0.02)
                return near(lift.state().position, HIGH)

            until(at_the_limit)
            assert stream.sent > 0
        # Its end: stopped by the block's exit, or stale already when a look at the state
        # held the loop past the stream's timeout (then the exit has no stream to stop).
        until(lambda: events.of("la1", "stream_stopped", "stream_stale", since=since))
        limited = events.of("la1", "limited", since=since)
        streams = 1 + len(events.of("la1", "stream_stale", since=since))  # a loaded host's
    assert 1 <= len(limited) <= streams, limited  # told once a stream
    assert all((e["joint"], e["limit"]) == ("lift", "max") for e in limited), limited
    with pytest.raises(bc.CommandError, match="outside the follow stream's with block"):
        stream.set(0.01)


# -- the joints message ----------------------------------------------------------------------


def test_the_joints_message_is_the_latest_and_a_feed_of_each(gwj, connect) -> None:
    client = connect(gwj)
    message = client.joints("gwj")
    assert isinstance(message, bc.JointsMessage) and message.gateway == "gwj"
    readings = {j.name: j for j in message.joints}
    assert set(readings) == {"lift", "la2"}
    assert isinstance(readings["lift"], bc.JointReading)
    assert (readings["lift"].device, readings["lift"].unit, readings["lift"].type) == (
        "la1", "m", "position")
    assert readings["la2"].unit == "raw"
    assert client.joints("gwj", max_age=0.0).ts >= message.ts  # the next one
    fed = list(client.joints_feed("gwj", timeout=0.5))
    assert fed and all(isinstance(m, bc.JointsMessage) for m in fed)
    assert [m.ts for m in fed] == sorted(m.ts for m in fed)
    with pytest.raises(bc.NoAnswerError, match=r"no joints message of nobody within 0\.2 s"):
        client.joints("nobody", timeout=0.2)
    assert list(client.joints_feed("nobody", timeout=0.2)) == []
    with pytest.raises(CommandError):
        client.joints("*")


def test_a_joints_message_that_is_not_one_is_skipped_by_the_latest_and_the_feed(
        gwj, connect, caplog) -> None:
    """A peer publishing junk on a gateway's joints key holds nobody up: what validates is
    taken, the rest left out with a warning."""
    client = connect(gwj)
    good = {"gateway": "junkgw", "ts": 1.0, "joints": []}
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.03):
            client.put("busgate/junkgw/joints", b'{"gateway": 1}')
            client.put("busgate/junkgw/joints", good)

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        with caplog.at_level(logging.WARNING, logger="busgate.client.messages"):
            assert client.joints("junkgw", max_age=0.0).gateway == "junkgw"
            fed = list(client.joints_feed("junkgw", timeout=0.3))
    finally:
        stop.set()
        publisher.join()
    assert fed and all(m.gateway == "junkgw" for m in fed)
    assert "joints messages of gateway 'junkgw' left out" in caplog.text


def test_a_joints_message_naming_another_gateway_is_left_out_by_the_latest_and_the_feed(
        gwj, connect, caplog) -> None:
    """A peer publishing on one gateway's joints key a message that names another (here
    ``gwj``'s joints passed off as ``posedgw``'s) was handed out as that gateway's: only a
    message naming the gateway asked is taken, the rest left out with a warning."""
    client = connect(gwj)
    own = {"gateway": "posedgw", "ts": 1.0, "joints": []}
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.03):
            client.put("busgate/posedgw/joints", {**own, "gateway": "gwj"})
            client.put("busgate/posedgw/joints", own)

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        with caplog.at_level(logging.WARNING, logger="busgate.client.messages"):
            latest = [client.joints("posedgw", max_age=0.0) for _ in range(3)]
            fed = list(client.joints_feed("posedgw", timeout=0.3))
    finally:
        stop.set()
        publisher.join()
    assert fed and all(m.gateway == "posedgw" for m in latest + fed)
    assert "joints messages of gateway 'posedgw' left out: it names gateway 'gwj'" in caplog.text


# -- a velocity joint (the demo's wheel) ----------------------------------------------------


def test_a_velocity_joint_turns_at_a_velocity_and_streams_joint_velocity(
        module_demo, connect) -> None:
    client = connect(module_demo.endpoint)
    wheel = client.joint("wheel")
    assert wheel.type == "velocity" and wheel.info.raw_per_turn == 10000
    #: 100 rpm in the joint's unit a second, by its calibration (docs/joints.md).
    at_100_rpm = 100 / 60 * wheel.info.raw_per_turn * wheel.info.scale
    patiently(lambda: wheel.device.send({"op": "set_mode", "mode": "velocity"}))
    patiently(wheel.device.enable)
    puts: list = []
    stop = client.subscribe("busgate/demo/dev/wheel/follow", lambda key, body: puts.append(body))
    try:
        reply = patiently(wheel.set_velocity, at_100_rpm)
        assert reply["state"]["target_speed_rpm"] == pytest.approx(100, abs=0.5)
        until(lambda: (wheel.state().velocity or 0) > at_100_rpm / 2)
        assert wheel.state().unit == wheel.unit
        with pytest.raises(bc.BadCommandError):
            wheel.move(1.0)  # a velocity joint takes no position
        with wheel.device.claim(ttl_s=2.0), wheel.follow() as stream:
            stream.set(at_100_rpm / 2)
            until(lambda: any(b.get("joint_velocity") == at_100_rpm / 2 for b in puts))
    finally:
        stop()
        patiently(wheel.set_velocity, 0.0)
        patiently(lambda: wheel.device.send({"op": "disable"}))  # as the demo starts it
    assert all("joint" not in body for body in puts)


# -- the asyncio face ------------------------------------------------------------------------


def test_the_asyncio_face_has_the_same_joints(gwj) -> None:
    async def main() -> None:
        async with bc.aio.connect(gwj, client_id="joints-aio") as client:
            lift = await client.joint("gwj/lift")
            assert isinstance(lift, bc.aio.Joint) and lift is lift.device.joint
            await patiently_async(lift.device.enable)
            await patiently_async(lift.move, 0.015)
            state = await lift.state()
            assert isinstance(state, bc.JointState) and state.unit == "m"
            async with lift.device.claim(ttl_s=2.0), lift.follow() as stream:
                assert isinstance(stream, bc.aio.JointFollow)
                stream.set(0.016)
                deadline = time.monotonic() + DEADLINE_S
                while not near((await lift.state()).position, 0.016):
                    assert time.monotonic() < deadline
                    await asyncio.sleep(0.02)
            assert (await client.joints("gwj")).gateway == "gwj"
            async for message in client.joints_feed("gwj", timeout=0.5):
                assert isinstance(message, bc.JointsMessage)
                break

    asyncio.run(asyncio.wait_for(main(), 60))


@pytest.mark.parametrize(("blocking", "awaiting"),
                         [(bc.Joint, bc.aio.Joint), (bc.JointFollow, bc.aio.JointFollow)],
                         ids=["Joint", "JointFollow"])
def test_a_joint_is_the_same_on_both_faces(blocking, awaiting) -> None:
    """As tests/test_client_faces.py holds every other class of the two faces."""
    assert public(blocking) == public(awaiting)
    for name in sorted(public(blocking)):
        mine, twin = (inspect.getattr_static(cls, name) for cls in (blocking, awaiting))
        assert kind(twin) in TWINS[kind(mine)], name
        if kind(twin) == "function":
            assert function_of(twin) is function_of(mine), name
        assert (inspect.signature(function_of(twin)).parameters
                == inspect.signature(function_of(mine)).parameters), name
    assert "joint" in public(bc.Device) and "joints_feed" in public(bc.aio.Client)


# -- the pieces, without a gateway -----------------------------------------------------------


def _info(*devices: dict) -> dict:
    return {"ok": True, "gateway": "gw1",
            "buses": [{"name": "uart0", "protocol": "inspire_la", "devices": list(devices)}]}


DESCRIBED = {"name": "lift", "type": "position", "unit": "m", "scale": SCALE, "offset": 0.0,
             "min": LOW, "max": HIGH, "max_velocity": None, "max_acceleration": None,
             "max_effort": None, "effort_unit": "N", "raw_per_turn": None, "configured": True}


#: A joint's state and its entry in the joints message, as a gateway publishes them.
STATE = {"name": "lift", "type": "position", "unit": "m", "position": 0.01, "velocity": None,
         "effort": None, "target": 0.012}
READING = {"name": "lift", "device": "la1", "type": "position", "unit": "m", "position": 0.01,
           "velocity": None, "effort": None, "ts": 1.0, "stale": False}
#: Each joint model and a message of it; its numbers are those whose value is a float or null.
JOINT_MODELS = [(bc.JointInfo, DESCRIBED), (bc.JointState, STATE), (bc.JointReading, READING)]


@pytest.mark.parametrize("number", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_a_joint_number_that_is_not_finite_is_refused(number: float) -> None:
    """A gateway never publishes NaN or an infinity in a joint (its values are computed
    finite, and its encoder would write one null): a peer's passed as a limit, a calibration
    or a position. Refused in ``info``'s joint, a state's and the joints message."""
    for model, valid in JOINT_MODELS:
        model.model_validate_json(json.dumps(valid))
        for field in [field for field, value in valid.items() if value is None or
                      type(value) is float]:
            with pytest.raises(ValidationError, match="finite number"):
                model.model_validate_json(json.dumps({**valid, field: number}))
    message = {"gateway": "gw8", "ts": 1.0, "joints": [READING]}
    for refused in ({**message, "ts": number}, {**message, "joints": [{**READING, "ts": number}]}):
        assert joints_message(json.dumps(refused).encode(), "gw8") is None


def test_a_joints_units_and_names_are_bounded() -> None:
    """A unit is a few letters (``m``, ``rad``, ``raw``; ``N``, ``A`` of an effort) and a
    joint's name one chunk of a key, as a device's: a peer's megabyte of either is refused,
    not kept for as long as the joint is."""
    texts = [(model, valid, field) for model, valid in JOINT_MODELS
             for field in ("unit", "effort_unit") if field in valid]
    for model, valid, field in texts:
        model.model_validate_json(json.dumps({**valid, field: "u" * 16}))
        for text in ("u" * 17, "u" * 2**20):
            with pytest.raises(ValidationError, match="at most 16 characters"):
                model.model_validate_json(json.dumps({**valid, field: text}))
    for name in ("x" * 65, "lift\n", ""):
        with pytest.raises(ValidationError, match="should match pattern"):
            bc.JointState.model_validate_json(json.dumps({**STATE, "name": name}))


def test_a_device_is_found_by_its_joints_name_and_an_unreadable_joint_is_left_out(
        caplog) -> None:
    la1 = {"name": "la1", "kind": "inspire_la", "joint": DESCRIBED}
    la2 = {"name": "la2", "kind": "inspire_la", "joint": {**DESCRIBED, "name": "grip",
                                                          "warp": 9}}
    la3 = {"name": "la3", "kind": "inspire_la"}  # a gateway of an earlier release
    infos = {"gw1": _info(la1, la2, la3)}
    found = locate(infos, "lift", "device", "k")
    assert (found.gateway, found.name, found.kind, found.joint.name) == (
        "gw1", "la1", "inspire_la", "lift")
    assert locate(infos, "gw1/la1", "device", "k").joint.max == HIGH
    with caplog.at_level(logging.WARNING, logger="busgate.client.base"):
        grip = locate(infos, "grip", "device", "k")  # found by name though not readable
    assert grip.name == "la2" and grip.joint is None
    assert "the joint of device 'la2' is left undescribed: warp" in caplog.text
    assert locate(infos, "la3", "device", "k").joint is None
    with pytest.raises(bc.UnknownDeviceError):
        locate(infos, "elbow", "device", "k")
    twice = {"gw1": _info(la1), "gw2": {**_info(la1), "gateway": "gw2"}}
    with pytest.raises(bc.AmbiguousError, match="gw1, gw2"):
        locate(twice, "lift", "device", "k")


def test_a_joint_no_info_describes_has_its_devices_name_and_no_stream() -> None:
    device = bc.Device(None, Found("gw1", "la3", "inspire_la"))  # type: ignore[arg-type]
    joint = device.joint
    assert (joint.name, joint.type, joint.unit, joint.info) == ("la3", None, None, None)
    assert repr(joint) == "<Joint gw1/la3 (not described)>" and joint is device.joint
    with pytest.raises(CommandError, match="gateway gw1 describes no joint of la3"):
        joint.follow()
    info = bc.JointInfo.model_validate(DESCRIBED)
    strange = bc.Device(None, Found("gw1", "x1", "warp_drive", info))  # type: ignore[arg-type]
    with pytest.raises(CommandError, match="warp_drive has no follow stream"):
        strange.joint.follow()


def test_a_joint_stream_carries_what_its_familys_stream_carries() -> None:
    """Positions for an Inspire LA or a DS servo whatever the type; for a ZLAC706, whose
    stream carries speeds in velocity mode and positions in position mode, its type's."""
    assert [follow_field(kind) for kind in ("inspire_la", "ds_servo", "zlac706", "warp")] == [
        "joint", "joint", "joint_velocity", None]
    assert [follow_field(kind, "velocity") for kind in ("inspire_la", "zlac706", "warp")] == [
        "joint", "joint_velocity", None]
    assert [follow_field(kind, "position") for kind in ("ds_servo", "zlac706")] == [
        "joint", "joint"]


def test_a_joints_message_that_is_not_one_is_left_out_with_one_warning(caplog) -> None:
    good = {"gateway": "gw9", "ts": 1.0, "joints": [
        {"name": "lift", "device": "la1", "type": "position", "unit": "m", "position": 0.01,
         "velocity": None, "effort": None, "ts": 1.0, "stale": False}]}
    assert joints_message(json.dumps(good).encode(), "gw9").joints[0].name == "lift"
    with caplog.at_level(logging.WARNING, logger="busgate.client.messages"):
        for payload in (b"not json", json.dumps({**good, "warp": 1}).encode()):
            assert joints_message(payload, "gw9") is None
    assert caplog.text.count("joints messages of gateway 'gw9' left out") == 1
