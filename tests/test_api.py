"""The gateway API without zenoh, on real buses: the LA simulator on a pty and the ZLAC706
simulator on python-can's virtual bus. Every refusal has its stable code and nothing refused
reaches a wire."""

from __future__ import annotations

import itertools
import json
import re
import threading
import time
from collections.abc import Callable

import can
import pytest
from pydantic import ValidationError

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.errors import CommandError
from busgate.gateway.api import commands
from busgate.gateway.api.commands import END_FENCE_S, MAX_PAYLOAD, GatewayApi
from busgate.gateway.api.taken import taken_under
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers import inspire_la as inspire_la_driver
from busgate.gateway.drivers import inspire_la_frames as la_frames
from busgate.gateway.scheduler import runner as runner_module
from busgate.gateway.scheduler.tickers import FRESH_PERIODS, MIN_FRESH_S
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.api import DEVICE_COMMAND_ADAPTERS
from busgate.schemas.config import CanBus, SerialBus
from busgate.schemas.validation import command_from_object, suggestion
from tests.conftest import wait_until

_channels = itertools.count()


class Clock:
    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return now() + self.offset


@pytest.fixture
def gateway(wait_for):
    """Two LA actuators on a simulated UART and one ZLAC706 on a virtual CAN bus."""
    simulator = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    simulator.start()
    channel = f"test-api-{next(_channels)}"
    can_sim = CanSimulator(zcan, [Zlac706CanDevice(5, heartbeat_ms=50)],
                           bus=can.Bus(interface="virtual", channel=channel)).start()
    # Reply margins with room for the simulators, which share this process and a loaded
    # machine's cores: a late reply is not what these tests are about.
    uart = SerialBus(name="uart0", transport="serial", port=simulator.port, baudrate=921_600,
                     reply_margin_ms=50,
                     devices=[{"name": "la1", "kind": "inspire_la", "id": 1},
                              {"name": "la2", "kind": "inspire_la", "id": 2}])
    can_bus = CanBus(name="can0", transport="can", interface="virtual", channel=channel,
                     reply_margin_ms=50,
                     devices=[{"name": "wheel", "kind": "zlac706", "id": 5, "heartbeat_ms": 50}])
    events = []
    runners = {bus.name: build_bus(bus, on_event=events.append).start() for bus in (uart, can_bus)}
    clock = Clock()
    for runner in runners.values():
        runner.authority.clock = clock  # claims' TTLs on a clock the tests can move
    api = GatewayApi("gw", runners, on_event=events.append)
    wait_for(lambda: all(driver.online for _, driver in api.devices.values()))
    yield api, simulator, can_sim, clock, events
    for runner in runners.values():
        runner.stop()
    simulator.stop()
    can_sim.stop()


def ask(api: GatewayApi, device: str, command) -> dict:
    payload = command if isinstance(command, bytes) else json.dumps(command).encode()
    return api.command(device, payload).result(10)


def accepted(api: GatewayApi, device: str, command) -> dict:
    reply = ask(api, device, command)
    assert reply["ok"], reply
    return reply


def code(reply: dict) -> str | None:
    return None if reply["ok"] else reply["error"]["code"]


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (b"\xff\xfe{}", "not_utf8"),
        (b"{op: move}", "not_json"),
        (b'{"op":"move","position":NaN}', "not_json"),
        (b'{"op":"move","position":Infinity}', "not_json"),
        (b"[1, 2]", "bad_command"),
        (b'{"op":"fly"}', "bad_command"),
        (b'{"op":"move"}', "bad_command"),
        (b'{"op":"move","position":10,"speed":3}', "bad_command"),
        (b'{"op":"move","position":"10"}', "bad_command"),
        (b'{"op":"move","position":1.5}', "bad_command"),
        (b'{"op":"move","position":2001}', "out_of_range"),
        (b'{"op":"move","position":-1}', "out_of_range"),
        (b'{"op":"move","position":10,"client":"no spaces"}', "bad_command"),
        (b'{"op":"' + b"x" * MAX_PAYLOAD + b'"}', "too_large"),
    ],
)
def test_hostile_payloads_are_refused_with_a_stable_code_and_never_sent(gateway, payload, expected):
    """Refused at once: the answer is there when ``command`` returns, before any bus thread
    could have seen the payload (no clock involved). Nothing reached the wire even once a
    later command to the same device was carried out (commands go out in order)."""
    api, simulator, *_ = gateway
    before = len(simulator.recorder.received())
    answer = api.command("la1", payload)
    assert answer.done(), "refused on the caller's thread, without a trip to the bus"
    reply = answer.result()
    assert code(reply) == expected and reply["error"]["message"]
    accepted(api, "la1", {"op": "status"})  # the proof that the bus had its chance
    sent = [r for r in simulator.recorder.received()[before:] if r.frame == "MoveCommand"]
    assert sent == []


def test_an_unknown_op_is_one_line_naming_the_op_it_most_likely_misspells(gateway) -> None:
    """Among the kind's ops and the gateway's (``release``); every op when none is close. The
    code is the schema's, as for any other malformed command."""
    api, *_ = gateway

    def refusal(message: str) -> dict:
        return {"ok": False, "error": {"code": "bad_command", "message": message}}

    assert ask(api, "la1", {"op": "mvoe", "position": 5}) == refusal(
        "unknown op `mvoe` for inspire_la (did you mean `move`?)")
    assert ask(api, "la1", {"op": "relase", "client": "c1"}) == refusal(
        "unknown op `relase` for inspire_la (did you mean `release`?)")
    ops = ", ".join(f"`{op}`" for op in DEVICE_COMMAND_ADAPTERS["zlac706"].core_schema["choices"])
    assert ask(api, "wheel", {"op": "fly"}) == refusal(
        f"unknown op `fly` for zlac706 (allowed: {ops})")
    # Never the op that undoes what was asked (``disable`` is close to ``enable``).
    assert ask(api, "wheel", {"op": "enabel"}) == refusal(
        "unknown op `enabel` for zlac706 (did you mean `enable`?)")
    # An op that is no string is named as sent, not as Python's `None` (an audit)
    for op, sent in ((None, "null"), (7, "7"), ([1], "[1]")):
        assert ask(api, "la1", {"op": op}) == refusal(
            f"`op` is a string naming the command, not {sent}")


@pytest.mark.parametrize(("device", "op", "instead"), [
    ("la1", "disable", "`pause` switches its power stage off"),
    ("wheel", "estop", "`disable` releases the motor"),
    ("wheel", "pause", "`disable` releases the motor"),
])  # fmt: skip
def test_another_familys_op_is_answered_with_what_does_its_deed_here(gateway, device, op,
                                                                       instead) -> None:
    """An LA has no ``disable`` (where ``enable`` was the op it was closest to)."""
    api, *_ = gateway
    reply = ask(api, device, {"op": op})
    assert reply["error"]["code"] == "bad_command"
    assert reply["error"]["message"].startswith(f"unknown op `{op}` for ")
    assert instead in reply["error"]["message"] and "did you mean" not in reply["error"]["message"]


@pytest.mark.parametrize(("fields", "words"), [
    ({"op": "velocity", "rpm": 1e300}, "velocity.rpm: must be at most 1000, not 1e+300"),
    ({"op": "velocity", "rpm": -2000}, "velocity.rpm: must be at least -1000, not -2000"),
    ({"op": "velocity", "rpm": 10**80},
     f"velocity.rpm: must be at most 1000, not {'1' + '0' * 39}…"),
    ({"op": "velocity", "rpm": True}, "velocity.rpm: Input should be a valid number"),
])  # fmt: skip
def test_a_number_past_a_bound_is_refused_with_the_bound_and_the_number(fields, words) -> None:
    """In the schema's own words otherwise (a bool is no number); a thousand digits are cut."""
    with pytest.raises(CommandError) as refused:
        command_from_object(DEVICE_COMMAND_ADAPTERS["zlac706"], fields, "zlac706")
    assert str(refused.value) == f"invalid command: {words}"


def test_a_refusal_repeats_a_letter_as_it_is_and_a_control_escaped() -> None:
    """``mové`` was repeated as ``mov\\xe9``, and the reply's JSON escaped that again."""
    with pytest.raises(CommandError) as refused:
        command_from_object(DEVICE_COMMAND_ADAPTERS["zlac706"], {"op": "mové\x1b[2J"}, "zlac706")
    assert str(refused.value).startswith("unknown op `mové\\u001b[2J` for zlac706")


def test_the_opposite_op_is_never_the_suggestion() -> None:
    assert suggestion("disable", ["enable", "move"]) == " (allowed: `enable`, `move`)"
    assert suggestion("disabel", ["disable", "enable"]) == " (did you mean `disable`?)"
    assert suggestion("enabel", ["enable"]) == " (did you mean `enable`?)"
    with pytest.raises(CommandError, match=r'^unknown op `enable` for ds_servo: `torque` with '
                                           r'`"on": true`'):
        command_from_object(DEVICE_COMMAND_ADAPTERS["ds_servo"], {"op": "enable"}, "ds_servo")


@pytest.mark.parametrize(("device", "command", "found_by"), [
    ("la1", {"op": "write", "index": 26, "data": "0000"}, "schema"),  # current_position: read only
    ("wheel", {"op": "write", "register": 0x10, "value": 0x10}, "codec"),  # control word: 0f, 1f
    ("la1", {"op": "set_overtemp", "temp_c": 64.9}, "codec"),  # below rewarm 60 °C + 5 °C
])  # fmt: skip
def test_an_encode_error_is_out_of_range_on_either_thread(gateway, device, command, found_by):
    """A value the wire cannot carry gets one code wherever it is found: by the schema's
    validator (the codec's own check) on the caller's thread, before anything reaches a bus,
    or by the codec on the bus thread, while the driver plans a command the schema took. And
    nothing of it is sent."""
    api, simulator, can_sim, *_ = gateway
    _, driver = api.devices[device]
    try:
        driver.commands.validate_python(command)
        schema_takes_it = True
    except ValidationError:
        schema_takes_it = False
    assert schema_takes_it == (found_by == "codec")
    answer = api.command(device, json.dumps(command).encode())
    if found_by == "schema":
        assert answer.done(), "refused on the caller's thread"
    assert code(answer.result(10)) == "out_of_range"
    accepted(api, device, {"op": "status"} if device == "la1" else {"op": "disable"})
    assert [r for r in simulator.recorder.received() if r.frame == "WriteCommand"] == []
    assert "005#00fa001000000010" not in {r.wire for r in can_sim.recorder.received()}


def test_unknown_device_and_bus(gateway):
    api, *_ = gateway
    assert code(ask(api, "la9", {"op": "status"})) == "unknown_device"
    assert code(api.bus_command("nope", b'{"op":"scan"}').result(10)) == "unknown_bus"


def test_a_command_comes_back_with_the_device_state(gateway):
    api, *_ = gateway
    reply = ask(api, "la1", {"op": "move", "position": 1500})
    assert reply["ok"] and reply["state"]["target"] == 1500 and reply["state"]["device"] == "la1"


def test_a_command_is_planned_once_its_effects_read_from_the_frames_it_plans(
        gateway, monkeypatch):
    """The bus thread builds a command's frames once: the authority judges their effects and
    the driver plans those same frames (they were built twice, for each)."""
    api, *_ = gateway
    built = []

    def counted(command, device_id):
        built.append(command)
        return la_frames.frames_for(command, device_id)

    monkeypatch.setattr(inspire_la_driver, "frames_for", counted)
    assert ask(api, "la1", {"op": "move", "position": 1400})["ok"]
    assert [type(c).__name__ for c in built] == ["Move"]


def test_a_claim_keeps_others_out_until_release_but_never_stops_an_estop(gateway):
    api, _, _, _clock, events = gateway
    accepted(api, "la1", {"op": "claim", "client": "alice", "ttl_s": 5})
    refused = ask(api, "la1", {"op": "move", "position": 100, "client": "bob"})
    assert code(refused) == "claimed"
    assert re.fullmatch(r"la1 is claimed by 'alice' \(its claim lapses in [45]\.\d s unless "
                        r"renewed\)", refused["error"]["message"])
    assert code(ask(api, "la1", {"op": "move", "position": 100})) == "claimed"
    accepted(api, "la1", {"op": "status", "client": "bob"})  # reads are never refused
    accepted(api, "la1", {"op": "move", "position": 100, "client": "alice"})
    assert code(ask(api, "la1", {"op": "release", "client": "bob"})) == "claimed"
    assert accepted(api, "la1", {"op": "release", "client": "alice"})["released"] is True
    accepted(api, "la1", {"op": "move", "position": 200, "client": "bob"})
    assert {e.type for e in events} >= {"claimed", "released"}
    # A release of nothing held is no release: answered so, and told to nobody.
    told = len(events)
    assert accepted(api, "la1", {"op": "release", "client": "nobody"})["released"] is False
    assert len(events) == told


def test_a_claim_lapses_after_its_ttl(gateway):
    api, _, _, clock, _ = gateway
    accepted(api, "la2", {"op": "claim", "client": "alice", "ttl_s": 1})
    assert code(ask(api, "la2", {"op": "move", "position": 5, "client": "bob"})) == "claimed"
    clock.offset = 1.5
    accepted(api, "la2", {"op": "move", "position": 5, "client": "bob"})


def test_estop_reaches_every_bus_ahead_of_everything(gateway):
    api, simulator, can_sim, *_ = gateway
    for future in api.stop_every_bus():
        future.result(10)
    la_frames = {r.wire for r in simulator.recorder.received()}
    assert la.encode(la.ControlCommand(1, la.ControlCode.ESTOP)).hex() in la_frames
    assert la.encode(la.ControlCommand(2, la.ControlCode.ESTOP)).hex() in la_frames
    assert "005#00fa00100000000f" in {r.wire for r in can_sim.recorder.received()}


def test_an_estop_returns_once_its_first_frame_went_on_every_bus(gateway, monkeypatch):
    """Its caller (a zenoh thread, then its log line) leaves the interpreter to the bus
    threads until each has had its e-stop's first exchange (runner rule 1); the bound on that
    wait, some milliseconds, is made long here so that a loaded host cannot reach it."""
    api, simulator, can_sim, *_ = gateway
    monkeypatch.setattr(runner_module, "ESTOP_SENT_S", 30.0)
    api.stop_every_bus()
    la_frames = {r.wire for r in simulator.recorder.received()}
    la_stops = {la.encode(la.ControlCommand(i, la.ControlCode.ESTOP)).hex() for i in (1, 2)}
    assert la_frames & la_stops
    assert "005#00fa00100000000f" in {r.wire for r in can_sim.recorder.received()}


def test_every_state_says_estopped_from_the_estop_until_the_reenable_command(wait_for, gateway):
    """The first state each device publishes after an e-stop says ``estopped`` and not
    ``enabled``; its re-enable command's reply and the states after say neither."""
    api, *_ = gateway
    published: list[tuple[str, dict]] = []
    for runner in api.runners.values():
        runner.telemetry.on_state = lambda device, state: published.append((device, state))
    for future in api.stop_every_bus():
        future.result(10)
    mark = len(published)

    def first_after(mark: int) -> dict[str, dict]:
        firsts: dict[str, dict] = {}
        for device, state in published[mark:]:
            firsts.setdefault(device, state)
        return firsts

    wait_for(lambda: first_after(mark).keys() == api.devices.keys())
    assert {d: (s["estopped"], s["enabled"]) for d, s in first_after(mark).items()} == {
        "la1": (True, False), "la2": (True, False), "wheel": (True, False)}
    for device, (_, driver) in api.devices.items():
        state = accepted(api, device, json.loads(driver.reenable_op))["state"]
        assert (state["estopped"], state["enabled"]) == (False, True), device
    mark = len(published)
    wait_for(lambda: first_after(mark).keys() == api.devices.keys())
    assert not any(state["estopped"] for _, state in published[mark:])


@pytest.mark.parametrize(("validation", "command"), [
    ("command_from_object", ("la1", {"op": "move", "position": 700})),
    ("group_command", ("uart0", {"op": "group_move",
                                 "targets": [{"device": "la1", "position": 700}]})),
])
def test_a_command_validated_while_an_e_stop_and_its_reset_came_is_refused(
        gateway, monkeypatch, validation, command) -> None:
    """A command an intake took off the network before an e-stop, still being validated
    when the e-stop and a reset came, moved its device after the reset: now it is refused
    ``estopped`` as it goes to its bus, a device's command as a bus's, and nothing is sent.
    One taken after the e-stop goes."""
    api, simulator, *_ = gateway
    validate = getattr(commands, validation)

    def stop_and_reset() -> None:  # another client, on another thread
        for future in api.stop_every_bus():
            future.result(10)
        accepted(api, "la1", json.loads(api.devices["la1"][1].reenable_op))

    def validate_meanwhile(*args, **kwargs):
        monkeypatch.setattr(commands, validation, validate)  # this command's alone
        elsewhere = threading.Thread(target=stop_and_reset)
        elsewhere.start()
        elsewhere.join(20)
        return validate(*args, **kwargs)

    monkeypatch.setattr(commands, validation, validate_meanwhile)
    target, body = command
    payload = json.dumps(body).encode()
    send = api.bus_command if target == "uart0" else api.command
    sent = len(simulator.recorder.received())
    replies: list[dict] = []

    def intake() -> None:  # a thread that took the command before the e-stop
        taken_under(api.estops)
        replies.append(send(target, payload).result(10))

    thread = threading.Thread(target=intake)
    thread.start()
    thread.join(30)
    assert [code(reply) for reply in replies] == ["estopped"]
    assert [r.frame for r in simulator.recorder.received()[sent:]
            if r.frame in ("MoveCommand", "GroupMoveCommand")] == []
    assert send(target, payload).result(10)["ok"]  # taken after it: it goes


def test_follow_is_validated_and_claimed_like_a_command(gateway):
    api, *_ = gateway
    assert api.follow("la1", b'{"position": 1200}') is None
    assert api.follow("la1", b'{"position": 9999}')["error"]["code"] == "out_of_range"
    assert api.follow("la1", b'{"rpm": 10}')["error"]["code"] == "bad_command"
    assert api.follow("ghost", b'{"position": 1}')["error"]["code"] == "unknown_device"
    accepted(api, "la2", {"op": "claim", "client": "alice"})
    assert api.follow("la2", b'{"position": 1, "client": "bob"}')["error"]["code"] == "claimed"


def test_a_client_that_goes_loses_its_claims_streams_and_speed(wait_for, gateway):
    api, _, can_sim, _, events = gateway
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        reply = ask(api, "wheel", op)
        assert reply["ok"], reply
    accepted(api, "wheel", {"op": "velocity", "rpm": 200, "client": "teleop"})
    accepted(api, "la1", {"op": "claim", "client": "teleop"})
    assert api.follow("la1", b'{"position": 700, "client": "teleop"}') is None
    before = len(can_sim.recorder.received())  # the start's release wrote 0 rpm already
    api.client_left("teleop")
    wait_for(lambda: "005#00fa001100000000" in {
        r.wire for r in can_sim.recorder.received()[before:]})
    accepted(api, "la1", {"op": "move", "position": 3, "client": "other"})
    wait_for(lambda: any(e.type == "stream_stopped" for e in events))


def test_a_client_that_goes_leaves_the_stream_another_client_drives_its_wheel_with(
        wait_for, gateway):
    """A one-shot speed's client is no longer the one moving the wheel once another's follow
    stream drives it: its going neither stops the wheel nor ends that stream (the deadman's
    0 rpm, a stop, ended it)."""
    api, _, can_sim, _, events = gateway
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        accepted(api, "wheel", op)
    accepted(api, "wheel", {"op": "velocity", "rpm": 200, "client": "teleop"})
    assert api.follow("wheel", b'{"rpm": 100, "client": "planner"}') is None
    streamed, stopped = "005#00fa001100000111", "005#00fa001100000000"

    def sent_since(start: int) -> list[str]:
        return [r.wire for r in can_sim.recorder.received()[start:]]

    wait_for(lambda: streamed in sent_since(0))
    before = len(can_sim.recorder.received())
    api.client_left("teleop")
    wait_for(lambda: sent_since(before).count(streamed) >= 3)
    assert stopped not in sent_since(before)
    assert not [e for e in events if e.type == "stream_stopped" or e.type == "stopped"]
    assert api.follow("wheel", b'{"rpm": 100, "client": "planner"}') is None


def follow_ticks(simulator) -> int:
    return sum(r.frame == "FollowCommand" for r in simulator.recorder.received())


def test_end_follow_ends_a_stream_at_once_claimed_like_a_target(wait_for, gateway):
    """Another client's end is refused ``claimed`` and the stream goes on; the holder's is
    answered at once and the stream ends ``stream_stopped`` with its reason, never stale."""
    api, simulator, _, _, events = gateway
    accepted(api, "la1", {"op": "claim", "client": "alice"})
    assert api.follow("la1", b'{"position": 700, "client": "alice"}') is None
    wait_for(lambda: follow_ticks(simulator) > 0)
    assert code(ask(api, "la1", {"op": "end_follow", "client": "bob"})) == "claimed"
    assert code(ask(api, "la1", {"op": "end_follow"})) == "claimed"
    assert api.follow("la1", b'{"position": 710, "client": "alice"}') is None  # still running
    assert ask(api, "la1", {"op": "end_follow", "client": "alice"}) == {"ok": True, "ended": True}
    assert "la1" not in api._stream_clients
    wait_for(lambda: any(e.type == "stream_stopped" for e in events))
    ended = follow_ticks(simulator)
    [stopped] = [e for e in events if e.type.startswith("stream_")]
    assert (stopped.device, stopped.type, stopped.fields) == (
        "la1", "stream_stopped", {"reason": "ended by alice"})
    accepted(api, "la1", {"op": "status"})  # a tick still due would have gone before it
    assert follow_ticks(simulator) == ended


@pytest.mark.parametrize("end", ["end_follow", "pause"])
def test_a_target_of_the_client_that_ended_the_stream_coming_just_after_is_dropped(wait_for,
                                                                                 gateway, end):
    """A target that reaches the gateway after its client's end_follow, or its stop on
    ``cmd`` (an LA's pause, which ends the stream too), was sent before it: it starts no
    stream (which would only go stale, or set the paused actuator going again). The same
    client's does once the fence has passed; another client's stop fences nothing of its."""
    api, simulator, _, _, events = gateway

    def stopped(count: int) -> None:
        wait_for(lambda: sum(e.type == "stream_stopped" for e in events) == count)

    assert api.follow("la2", b'{"position": 700, "client": "alice"}') is None
    wait_for(lambda: follow_ticks(simulator) > 0)
    accepted(api, "la2", {"op": end, "client": "alice"})
    stopped(1)
    ended = follow_ticks(simulator)
    assert api.follow("la2", b'{"position": 701, "client": "alice"}') is None
    time.sleep(END_FENCE_S)
    assert follow_ticks(simulator) == ended  # nothing started
    assert api.follow("la2", b'{"position": 702, "client": "alice"}') is None  # past the fence
    wait_for(lambda: follow_ticks(simulator) > ended)
    accepted(api, "la2", {"op": "pause", "client": "bob"})
    stopped(2)
    ended = follow_ticks(simulator)
    assert api.follow("la2", b'{"position": 703, "client": "alice"}') is None
    wait_for(lambda: follow_ticks(simulator) > ended)
    accepted(api, "la2", {"op": "end_follow", "client": "alice"})
    stopped(3)
    assert [e.type for e in events if e.type.startswith("stream_")] == ["stream_stopped"] * 3


def test_numbered_targets_are_ordered_against_the_end_by_their_seq_not_by_a_fence(
        wait_for, gateway, monkeypatch):
    """With ``seq`` on the targets and the end (as the SDK sends them), the order holds by
    construction: a target numbered below the end is dropped however late it comes (the
    fence shrunk to nothing cannot let it through), one numbered above starts a new stream at
    once (the fence would have dropped it for half a second)."""
    monkeypatch.setattr(commands, "END_FENCE_S", 0.0)
    api, simulator, _, _, events = gateway
    assert api.follow("la2", b'{"position": 700, "client": "carol", "seq": 1}') is None
    wait_for(lambda: follow_ticks(simulator) > 0)
    accepted(api, "la2", {"op": "end_follow", "client": "carol", "seq": 3})
    wait_for(lambda: any(e.type == "stream_stopped" for e in events))
    time.sleep(0.05)  # past the (shrunk) fence: only the numbers can tell
    assert api.follow("la2", b'{"position": 701, "client": "carol", "seq": 2}') is None
    accepted(api, "la2", {"op": "status"})
    ended = follow_ticks(simulator)
    accepted(api, "la2", {"op": "status"})  # a stream started would have ticked by now
    assert follow_ticks(simulator) == ended
    monkeypatch.setattr(commands, "END_FENCE_S", 10.0)  # a fence could not let this one by
    assert api.follow("la2", b'{"position": 702, "client": "carol", "seq": 4}') is None
    wait_for(lambda: follow_ticks(simulator) > ended)
    accepted(api, "la2", {"op": "end_follow", "client": "carol", "seq": 5})
    wait_for(lambda: sum(e.type == "stream_stopped" for e in events) == 2)


def test_a_target_checked_as_the_stream_ends_is_handed_to_the_bus_before_the_end(wait_for,
                                                                                 gateway):
    """zenoh takes a target and its client's end_follow on two threads. A target that passed
    the fence before the end came is handed to the bus before the end is: the stream that
    target starts is the one the end stops, and nothing goes stale (a target held between
    its check and its hand-over once started a stream after the end)."""
    api, _, _, _, events = gateway
    runner, _ = api.devices["la1"]
    in_check, go_on = threading.Event(), threading.Event()
    check = runner.authority.check

    def held_check(*args, **kwargs):
        in_check.set()
        assert go_on.wait(10)
        return check(*args, **kwargs)

    runner.authority.check = held_check
    target = threading.Thread(target=api.follow, args=("la1", b'{"position": 700, "client": "a"}'))
    target.start()
    assert in_check.wait(10)
    runner.authority.check = check
    end = threading.Thread(target=ask, args=(api, "la1", {"op": "end_follow", "client": "a"}))
    end.start()
    end.join(0.2)
    assert end.is_alive()  # the end waits for the target checked before it
    go_on.set()
    target.join(10)
    end.join(10)
    wait_for(lambda: any(e.type == "stream_stopped" for e in events))
    time.sleep(3 * max(FRESH_PERIODS * 0.050, MIN_FRESH_S))  # a stale stream would be seen
    assert [e.type for e in events if e.type.startswith("stream_")] == ["stream_stopped"]


def on_in_velocity_mode(api: GatewayApi, can_sim) -> Callable[[int], list[str]]:
    """The wheel enabled in velocity mode; what gives the speed writes (register 0x11) the
    simulator received since its ``since``-th frame."""
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        accepted(api, "wheel", op)

    def speed_writes(since: int = 0) -> list[str]:
        return [r.wire for r in can_sim.recorder.received()[since:]
                if r.wire.startswith("005#00fa0011")]

    return speed_writes


def test_end_follow_brings_a_velocity_stream_to_0_rpm_and_an_estop_never_refuses_it(wait_for,
                                                                                   gateway):
    api, _, can_sim, _, events = gateway
    speed_writes = on_in_velocity_mode(api, can_sim)

    assert api.follow("wheel", b'{"rpm": 120}') is None
    wait_for(lambda: any(wire != "005#00fa001100000000" for wire in speed_writes()))
    mark = len(can_sim.recorder.received())
    assert ask(api, "wheel", {"op": "end_follow"}) == {"ok": True, "ended": True}
    wait_for(lambda: "005#00fa001100000000" in speed_writes(mark))
    assert [(e.type, e.fields) for e in events if e.type.startswith("stream_")] == [
        ("stream_stopped", {"reason": "ended"})]
    for future in api.stop_every_bus():
        future.result(10)
    assert ask(api, "la2", {"op": "end_follow"}) == {"ok": True, "ended": True}


def test_a_one_shot_target_for_a_streamed_device_is_refused_and_a_stop_ends_the_stream(
        wait_for, gateway):
    """A stream's next tick would overwrite a one-shot target, and its 0 rpm when it went
    stale would stop it (an outside audit: a velocity answered ok, then 0 rpm): refused
    ``busy``, nothing sent. A stop ends the stream, or its next tick would undo it."""
    api, simulator, can_sim, _, events = gateway
    speed_writes = on_in_velocity_mode(api, can_sim)

    streaming = threading.Event()

    def stream() -> None:  # the streams' client, a target each 20 ms: never stale
        while not streaming.wait(0.02):
            api.follow("wheel", b'{"rpm": 120}')
            api.follow("la1", b'{"position": 700}')

    client = threading.Thread(target=stream)
    client.start()
    try:
        wait_for(lambda: any(wire != "005#00fa001100000000" for wire in speed_writes()))
        wait_for(lambda: follow_ticks(simulator) > 0)
        streamed = speed_writes()[-1]
        mark = len(can_sim.recorder.received())
        refused = ask(api, "wheel", {"op": "velocity", "rpm": 50})
        assert code(refused) == "busy" and "end_follow" in refused["error"]["message"]
        assert code(ask(api, "la1", {"op": "move", "position": 3})) == "busy"
        time.sleep(0.1)
        assert set(speed_writes(mark)) == {streamed}
        assert not [r for r in simulator.recorder.received() if r.frame == "MoveCommand"]
        assert not [e for e in events if e.type.startswith("stream_")]
        # the stops, the streams still fed: each ends its stream (the client's next target
        # starts another, as after an end_follow)
        accepted(api, "la1", {"op": "pause"})
        accepted(api, "wheel", {"op": "velocity", "rpm": 0})
        wait_for(lambda: len([e for e in events if e.type.startswith("stream_")]) == 2)
    finally:
        streaming.set()
        client.join()
    assert [(e.device, e.type, e.fields) for e in events if e.type.startswith("stream_")][:2] == [
        ("la1", "stream_stopped", {"reason": "stopped by a command"}),
        ("wheel", "stream_stopped", {"reason": "stopped by a command"})]


def test_group_move_is_one_broadcast_frame_and_scan_finds_the_actuators(wait_for, gateway):
    api, simulator, *_ = gateway
    reply = api.bus_command("uart0", json.dumps({"op": "group_move", "targets": [
        {"device": "la1", "position": 400}, {"device": "la2", "position": 600}]}).encode())
    assert reply.result(10)["ok"]

    def groups():
        return [r for r in simulator.recorder.received() if r.frame == "GroupMoveCommand"]

    wait_for(lambda: groups())  # the frame has no reply: the simulator may read it a bit later
    found = api.bus_command("uart0", b'{"op":"scan","ids":[1,2,3]}').result(10)
    assert found["ok"] and [f["id"] for f in found["found"]] == [1, 2]
    assert len(groups()) == 1, "one frame, even once the scan after it was answered"
    refused = api.bus_command("can0", json.dumps({"op": "group_move", "targets": [
        {"device": "wheel", "position": 1}]}).encode()).result(10)
    assert code(refused) == "bad_command"


def test_info_lists_buses_devices_and_their_state(gateway):
    api, *_ = gateway
    info = api.info()
    assert info["ok"] and info["gateway"] == "gw"
    buses = {bus["name"]: bus for bus in info["buses"]}
    assert buses["uart0"]["protocol"] == "inspire_la"
    assert [d["name"] for d in buses["uart0"]["devices"]] == ["la1", "la2"]
    assert buses["can0"]["devices"][0]["kind"] == "zlac706"


def test_a_reset_of_every_bus_says_which_bus_it_could_not_reset(tmp_path, caplog) -> None:
    """A reset while a bus was down (in a worker: while the worker was down) was told as a
    reset of every bus, and its devices stayed e-stopped with nothing said (an audit's). The
    bus whose reset fails says so in a line of its own."""
    bus = SerialBus(name="uart9", transport="serial", port=str(tmp_path / "gone"), baudrate=921_600,
                    devices=[{"name": "la9", "kind": "inspire_la", "id": 1}])
    runner = build_bus(bus).start()
    try:
        api = GatewayApi("gw", {"uart9": runner})
        with caplog.at_level("WARNING", logger=commands.__name__):
            (reset,) = api.reset_every_bus("c1")[0]
            assert isinstance(reset.exception(timeout=5), Exception)

            def said() -> list[str]:  # told by the future's callback, after its waiters wake
                return [r.getMessage() for r in caplog.records if "not reset" in r.getMessage()]

            wait_until(said, what="the bus's line")
        assert said()[0].startswith(
            "e-stop reset: bus uart9 not reset, its devices still e-stopped (reset again once "
            "it is back): "), said()
    finally:
        runner.stop()
