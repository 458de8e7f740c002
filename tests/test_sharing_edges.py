"""Sharing at the edges of the API, on real buses (LA and DS simulators on ptys, a ZLAC706 on
python-can's virtual bus): a request is authorised by the devices its frames address, never by
the key it came through; motion to an e-stopped device is refused ``estopped`` on every path;
a command answered with an error is never carried out; a scan is bounded and interleaves;
hostile JSON gets exactly one reply with its code.

"Nothing reached the wire" is checked after a later command was answered on the same bus, so
the bus had every chance to send what it should not have."""

from __future__ import annotations

import json

import pytest

from busgate.codecs import inspire_la as la
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.scheduler import runner as runner_module
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from tests.simulated_buses import la_bus, simulated_gateway

TARGET_INDEX = la.REGISTERS[la.TARGET_POSITION].address


#: Reply timing is not what these tests are about: room for a loaded host.
MARGIN_MS = 50


@pytest.fixture
def gateway():
    """Three LA actuators, two DS servos, one ZLAC706, each family on its own bus."""
    with simulated_gateway(margin_ms=MARGIN_MS) as world:
        yield world.api, world.la_sim, world.ds_sim


def ask(api: GatewayApi, device: str, command: dict | bytes) -> dict:
    payload = command if isinstance(command, bytes) else json.dumps(command).encode()
    return api.command(device, payload).result(5)


def ask_bus(api: GatewayApi, bus: str, command: dict | bytes, timeout: float = 5) -> dict:
    payload = command if isinstance(command, bytes) else json.dumps(command).encode()
    return api.bus_command(bus, payload).result(timeout)


def code(reply: dict | None) -> str | None:
    return None if reply is None or reply["ok"] else reply["error"]["code"]


def accepted(api: GatewayApi, device: str, command: dict) -> dict:
    reply = ask(api, device, command)
    assert reply["ok"], reply
    return reply


def frames(simulator: SerialSimulator, *names: str) -> list:
    return [r for r in simulator.recorder.received() if r.frame in names]


def settled(api: GatewayApi, device: str) -> None:
    """A later exchange on the device's bus was answered: whatever was queued before it has
    gone out (or never will)."""
    accepted(api, device, {"op": "ping"} if device.startswith("arm") else {"op": "status"})


# -- 1. authorise by effect ------------------------------------------------------------------

GROUP_OPS = [
    ("la1", {"op": "group_move", "client": "A", "targets": [{"id": 2, "position": 1507}]}),
    ("la1", {"op": "group_follow", "client": "A", "targets": [{"id": 2, "position": 1507}]}),
    ("la3", {"op": "group_move", "targets": [{"id": 3, "position": 9}, {"id": 2, "position": 9}]}),
]


@pytest.mark.parametrize(("key", "command"), GROUP_OPS)
def test_a_group_op_on_a_device_key_is_checked_on_every_device_it_moves(gateway, key, command):
    api, la_sim, _ = gateway
    accepted(api, "la2", {"op": "claim", "client": "B"})
    refused = ask(api, key, command)
    assert code(refused) == "claimed" and "'B'" in refused["error"]["message"]
    settled(api, "la1")
    assert frames(la_sim, "GroupMoveCommand", "GroupFollowCommand") == []
    accepted(api, key, command | {"client": "B"})  # the holder may


@pytest.mark.parametrize("bus, targets, held", [
    ("uart0", [{"device": "la1", "position": 5}, {"device": "la2", "position": 5}], "la2"),
    ("uart1", [{"device": "arm1", "position": 5}, {"device": "arm2", "position": 5}], "arm1"),
])
def test_a_bus_group_move_needs_the_claim_of_every_device_it_moves(gateway, bus, targets, held):
    api, la_sim, ds_sim = gateway
    accepted(api, held, {"op": "claim", "client": "B"})
    refused = ask_bus(api, bus, {"op": "group_move", "client": "A", "targets": targets})
    assert code(refused) == "claimed" and held in refused["error"]["message"]
    settled(api, held)
    assert frames(la_sim, "GroupMoveCommand") == frames(ds_sim, "SyncWrite") == []
    assert ask_bus(api, bus, {"op": "group_move", "client": "B", "targets": targets})["ok"]


def test_a_group_frame_sent_through_one_device_tells_every_device_it_moves(gateway):
    """An ACTION starts every servo's stored move, a SYNC WRITE and an LA group move target
    others than the device whose command sent them: each of those knows it, where only the
    sender did (arm2's stored move stayed pending for ever; a paused la1, moved, said paused)."""
    api, _, _ = gateway
    accepted(api, "arm1", {"op": "move", "position": 1111, "deferred": True})
    accepted(api, "arm2", {"op": "move", "position": 2222, "deferred": True})
    accepted(api, "arm1", {"op": "action"})
    state = accepted(api, "arm2", {"op": "ping"})["state"]
    assert (state["pending_target"], state["target"]) == (None, 2222)
    accepted(api, "arm1", {"op": "group_move", "targets": [{"id": 1, "position": 1300},
                                                           {"id": 2, "position": 3300}]})
    assert accepted(api, "arm2", {"op": "ping"})["state"]["target"] == 3300
    accepted(api, "la1", {"op": "pause"})
    accepted(api, "la3", {"op": "group_move", "targets": [{"id": 1, "position": 900}]})
    assert accepted(api, "la1", {"op": "status"})["state"]["power"] == "on"


def test_a_frame_to_an_id_no_device_is_configured_with_is_refused(gateway):
    api, la_sim, _ = gateway
    refused = ask(api, "la1", {"op": "group_move", "targets": [{"id": 9, "position": 1}]})
    assert code(refused) == "unknown_device" and "9" in refused["error"]["message"]
    settled(api, "la1")
    assert frames(la_sim, "GroupMoveCommand") == []


def test_a_broadcast_is_checked_on_every_device_of_its_bus(gateway):
    api, _, ds_sim = gateway
    accepted(api, "arm2", {"op": "claim", "client": "B"})
    assert code(ask(api, "arm1", {"op": "action", "client": "A"})) == "claimed"
    settled(api, "arm1")
    assert frames(ds_sim, "Action") == []


def test_motion_to_an_estopped_actuator_is_refused_on_every_path(gateway):
    api, la_sim, _ = gateway
    accepted(api, "la2", {"op": "estop"})
    paths = {
        "move": ask(api, "la2", {"op": "move", "position": 1500}),
        "raw write of the target": ask(api, "la2", {"op": "write", "index": TARGET_INDEX,
                                                    "data": "dc05"}),
        "group op on another key": ask(api, "la1", {"op": "group_move", "targets": [
            {"id": 1, "position": 5}, {"id": 2, "position": 1500}]}),
        "bus group move": ask_bus(api, "uart0", {"op": "group_move", "targets": [
            {"device": "la2", "position": 1500}]}),
        "follow": api.follow("la2", b'{"position": 1500}'),
    }
    for path, reply in paths.items():
        assert code(reply) == "estopped", path
        assert '{"op":"enable"}' in reply["error"]["message"], path
    settled(api, "la2")
    moves = frames(la_sim, "MoveCommand", "WriteCommand", "GroupMoveCommand", "FollowCommand")
    assert moves == []
    accepted(api, "la2", {"op": "enable"})
    accepted(api, "la2", {"op": "move", "position": 1500})


def test_after_a_gateway_estop_every_kind_waits_for_its_reenable_op(gateway):
    api, _, _ = gateway
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        accepted(api, "wheel", op)
    for stopped in api.stop_every_bus():
        stopped.result(5)
    for device, motion, reenable in [
        ("la1", {"op": "move", "position": 10}, {"op": "enable"}),
        ("arm1", {"op": "move", "position": 100}, {"op": "torque", "on": True}),
        ("wheel", {"op": "velocity", "rpm": 50}, {"op": "enable"}),
    ]:
        refused = ask(api, device, motion)
        assert code(refused) == "estopped", device
        message = refused["error"]["message"]
        assert 'send {"op":"reset_estop"} to reset it' in message, message
        assert json.dumps(reenable, separators=(",", ":")) in message
        accepted(api, device, reenable)
        accepted(api, device, motion)
    accepted(api, "wheel", {"op": "velocity", "rpm": 0})  # a stop is never refused


# -- 2. no frame after a failure reply -------------------------------------------------------


def test_a_command_not_started_by_its_deadline_is_answered_busy_and_never_sent(
        gateway, monkeypatch):
    api, la_sim, _ = gateway
    monkeypatch.setattr(runner_module, "COMMAND_START_S", -1.0)  # every deadline has passed
    refused = ask(api, "la1", {"op": "move", "position": 1234})
    assert code(refused) == "busy" and "nothing was sent" in refused["error"]["message"]
    monkeypatch.undo()
    settled(api, "la1")
    assert [r for r in frames(la_sim, "MoveCommand") if "d204" in r.wire] == []


def test_a_command_cancelled_before_it_started_is_never_sent(wait_for):
    with SerialSimulator(la, [InspireLaDevice(i) for i in (1, 2, 3)],
                         baudrate=921_600) as la_sim:
        # Not started: the command waits in its inbox.
        runner = build_bus(la_bus(la_sim.port, MARGIN_MS))
        api = GatewayApi("gw", {"uart0": runner})
        pending = api.command("la1", b'{"op":"move","position":1234}')
        assert pending.cancel()  # what the bridge does when its reply guard fires
        runner.start()
        try:
            wait_for(lambda: runner.drivers["la1"].online)
            settled(api, "la1")
            assert [r for r in frames(la_sim, "MoveCommand") if "d204" in r.wire] == []
        finally:
            runner.stop()


@pytest.mark.parametrize(("ids", "expected"), [
    ([1, 1], "bad_command"),
    (list(range(1, 256)), "out_of_range"),
    ([1] * 10_000, "out_of_range"),
    ([0], "out_of_range"),
    ([], "out_of_range"),
])
def test_a_scan_is_bounded(gateway, ids, expected):
    api, _, _ = gateway
    refused = api.bus_command("uart0", json.dumps({"op": "scan", "ids": ids}).encode())
    assert refused.done(), "refused by the API itself: the bus never saw it"
    assert code(refused.result()) == expected


#: 40 ids: with the tests' 50 ms reply margin, the most a scan fits in its 4 s.
SCAN_40 = json.dumps({"op": "scan", "ids": list(range(1, 41))}).encode()


def test_a_scan_interleaves_with_commands(gateway):
    api, _, _ = gateway
    scanning = api.bus_command("uart0", SCAN_40)
    moved = api.command("la1", b'{"op":"move","position":321}')
    assert moved.result(5)["ok"]
    assert not scanning.done(), "the move did not wait for the scan of 40 ids"
    found = scanning.result(15)
    assert found["ok"] and [f["id"] for f in found["found"]] == [1, 2, 3]


def test_an_estop_ends_a_scan_with_a_reply(gateway):
    api, _, _ = gateway
    scanning = api.bus_command("uart0", SCAN_40)
    for stopped in api.stop_every_bus():
        stopped.result(5)
    assert code(scanning.result(5)) == "estopped"


# -- 3. one reply per query, with its code ----------------------------------------------------

DEEP = b"[" * 30_000 + b"]" * 30_000  # 60 KB: under the size limit


@pytest.mark.parametrize(("payload", "expected"), [
    (b'{"op":"move","a":' + b"[" * 1001 + b"]" * 1001 + b"}", "bad_command"),
    (DEEP, "bad_command"),
    (b'{"op":"move","position":3000,"position":100}', "bad_command"),
    (b'{"op":"move","position":1e309}', "not_json"),
    (b'{"op":"move","position":-1e309}', "not_json"),
])
def test_hostile_json_on_a_device_key_gets_its_code(gateway, payload, expected):
    api, la_sim, _ = gateway
    assert code(ask(api, "la1", payload)) == expected
    settled(api, "la1")
    assert frames(la_sim, "MoveCommand") == []


@pytest.mark.parametrize(("payload", "expected"), [
    (b'{"op":["group_move"]}', "bad_command"),
    (b'{"op":{"a":1}}', "bad_command"),
    (b'{"op":null}', "bad_command"),
    (DEEP, "bad_command"),
    (b'{"op":"scan","ids":[1],"ids":[2]}', "bad_command"),
])
def test_hostile_json_on_a_bus_key_gets_its_code(gateway, payload, expected):
    api, _, _ = gateway
    assert code(ask_bus(api, "uart0", payload)) == expected


@pytest.mark.parametrize("client", ['["x"]', "7", '"a/**"', '""', "null"])
def test_the_follow_key_validates_its_client_as_strictly_as_cmd(gateway, client):
    api, _, _ = gateway
    payload = f'{{"position": 500, "client": {client}}}'.encode()
    # the command first: a move for a device a stream follows is refused ``busy``
    command = ask(api, "la1", payload.replace(b"{", b'{"op": "move", ', 1))
    follow = api.follow("la1", payload)
    if client == "null":  # no client at all, on both
        assert follow is None and command["ok"]
    else:
        assert code(follow) == code(command) == "bad_command"


def test_a_follow_target_is_refused_while_another_client_holds_the_device(gateway):
    api, la_sim, _ = gateway
    accepted(api, "la3", {"op": "claim", "client": "B"})
    assert code(api.follow("la3", b'{"position": 700}')) == "claimed"
    assert code(api.follow("la3", b'{"position": 700, "client": "A"}')) == "claimed"
    settled(api, "la3")
    assert frames(la_sim, "FollowCommand", "GroupFollowCommand") == []


def test_a_bad_joint_follow_target_says_so_as_a_bad_kind_payload_does(gateway):
    """A joint's was said to be an "invalid command"."""
    api, _, _ = gateway
    for payload in (b'{"joint": "far"}', b'{"position": "far"}'):
        reply = api.follow("la1", payload)
        assert code(reply) == "bad_command", reply
        assert reply["error"]["message"].startswith("invalid follow target: "), reply
    both = api.follow("la1", b'{"position": 100, "joint": 0.001}')  # was "Extra inputs …"
    assert both["error"]["message"] == (
        "invalid follow target: a follow target in joint units takes joint or joint_velocity, "
        "not position beside it (one in the device's own units gives those alone)")


def test_require_claim_refuses_what_needs_a_claim_the_client_does_not_hold(gateway):
    """A client that claimed sends ``require_claim``: once its claim is gone, what needs the
    claim is refused ``not_claimed`` on every path, and reads and stops still go through."""
    api, la_sim, _ = gateway
    needing = {"client": "A", "require_claim": True}
    assert code(ask(api, "la2", {"op": "move", "position": 1601, **needing})) == "not_claimed"
    assert code(api.follow("la2", json.dumps({"position": 1602, **needing}).encode())) == \
        "not_claimed"
    assert code(ask_bus(api, "uart0", {"op": "group_move", **needing,
                                       "targets": [{"device": "la2", "position": 1603}]})) == \
        "not_claimed"
    # The gateway's own ops that need the claim (ending a stream, an e-stop's reset) too:
    # they took no notice of require_claim.
    assert code(ask(api, "la2", {"op": "end_follow", **needing})) == "not_claimed"
    assert code(ask(api, "la2", {"op": "reset_estop", **needing})) == "not_claimed"
    assert accepted(api, "la2", {"op": "status", **needing})  # a read
    assert accepted(api, "la2", {"op": "pause", **needing})  # a stop
    accepted(api, "la2", {"op": "claim", "client": "B"})  # another holds it: that is said
    assert code(ask(api, "la2", {"op": "move", "position": 1604, **needing})) == "claimed"
    accepted(api, "la2", {"op": "release", "client": "B"})
    accepted(api, "la2", {"op": "claim", "client": "A"})
    accepted(api, "la2", {"op": "move", "position": 1605, **needing})
    settled(api, "la2")
    moves = frames(la_sim, "MoveCommand", "GroupMoveCommand", "FollowCommand",
                   "GroupFollowCommand")
    sent = {p for p in range(1601, 1606) if any(p.to_bytes(2, "little").hex() in r.wire
                                               for r in moves)}
    assert sent == {1605}  # only what the held claim allowed reached the wire


def test_an_id_another_device_of_the_bus_has_is_refused_and_nothing_goes_out(gateway):
    """A ``set_id``, a raw write of the id and a DS servo's factory reset (its factory id is
    1) to an id another device of the bus had were carried out: both devices then took every
    frame sent to it, so a move to one moved the other, whoever held its claim."""
    api, la_sim, ds_sim = gateway
    for device, command, clash in [
        ("la1", {"op": "set_id", "new_id": 2}, "la1 would take id 2, la2's on bus uart0"),
        ("la3", {"op": "write", "index": 2, "data": "01"}, "la3 would take id 1, la1's"),
        ("arm1", {"op": "set_id", "new_id": 2}, "arm1 would take id 2, arm2's on bus uart1"),
        ("arm2", {"op": "write", "address": 5, "data": "01"}, "arm2 would take id 1, arm1's"),
        ("arm2", {"op": "reset"}, "arm2 would take id 1, arm1's"),
    ]:
        refused = ask(api, device, command)
        assert code(refused) == "out_of_range", (device, refused)
        assert refused["error"]["message"].startswith(clash), refused
    assert refused["error"]["message"] == (
        "arm2 would take id 1, arm1's on bus uart1: two devices of one id both take every "
        "frame sent to it; give it an id no device of the bus has")
    refused = ask(api, "arm1", {"op": "set_id", "new_id": 1})  # its own: no clash, no change
    assert refused["error"]["message"] == "servo arm1 already has id 1"
    assert frames(la_sim, "WriteCommand") == [] and frames(ds_sim, "Write", "Reset") == []
    ids = {name: driver.device_id for name, (_, driver) in api.devices.items()}
    assert ids == {"la1": 1, "la2": 2, "la3": 3, "arm1": 1, "arm2": 2, "wheel": 5}


def test_a_ds_servo_switched_on_by_a_raw_write_is_out_of_its_estop_and_a_reset_is_refused(
        gateway):
    """A raw write of the torque switch is the torque op's frame: it let an e-stopped servo
    drive its shaft while the gateway still said it was e-stopped. Now it counts as the op
    does (as the ZLAC706's raw control word does), and a factory reset, which switches torque
    on, is refused while e-stopped as a move is."""
    api, _, ds_sim = gateway
    for stopped in api.stop_every_bus():
        stopped.result(5)
    assert code(ask(api, "arm2", {"op": "reset"})) == "estopped"
    assert frames(ds_sim, "Reset") == []
    _, servo = api.devices["arm2"]
    assert servo.estopped
    accepted(api, "arm2", {"op": "write", "address": 40, "data": "01"})
    assert not servo.estopped
    accepted(api, "arm2", {"op": "move", "position": 1000})
    accepted(api, "arm2", {"op": "write", "address": 40, "data": "00"})  # torque off: a stop


@pytest.mark.parametrize(("bus", "command", "expected"), [
    ("uart0", {"op": "group_move", "targets": [{"device": "ghost", "position": 5}]},
     "unknown_device"),
    ("uart0", {"op": "group_move", "targets": [{"device": "arm1", "position": 5}]},
     "unknown_device"),  # a device of another bus
    ("uart0", {"op": "group_move", "targets": [{"device": "la1", "position": 5,
                                                "time_ms": 100}]}, "bad_command"),
    ("uart0", {"op": "group_move", "targets": [{"device": "la1", "position": 9999}]},
     "out_of_range"),
    ("uart0", {"op": "group_move", "targets": []}, "out_of_range"),
    ("can0", {"op": "group_move", "targets": [{"device": "wheel", "position": 1}]},
     "bad_command"),  # a ZLAC706 frame addresses one node: no group move
    ("nope", {"op": "group_move", "targets": [{"device": "la1", "position": 1}]},
     "unknown_bus"),
])
def test_a_group_move_the_bus_cannot_make_is_refused(gateway, bus, command, expected):
    api, la_sim, _ = gateway
    assert code(ask_bus(api, bus, command)) == expected
    settled(api, "la1")
    assert frames(la_sim, "GroupMoveCommand") == []


def test_claims_releases_and_lost_claims_are_logged(gateway, caplog):
    """(The e-stop's line is the bridge's: ``test_mutants_api``.)"""
    api, _, _ = gateway
    with caplog.at_level("INFO"):
        accepted(api, "la1", {"op": "claim", "client": "A", "ttl_s": 30})
        accepted(api, "la1", {"op": "release", "client": "A"})
        accepted(api, "la2", {"op": "claim", "client": "B"})
        api.client_left("B")
    lines = [record.getMessage() for record in caplog.records]
    assert "device la1 claimed by A for 30.0 s" in lines
    assert "device la1 released by A" in lines
    assert "device la2: claim of B lost (client gone)" in lines
