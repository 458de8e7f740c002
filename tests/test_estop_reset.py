"""The e-stop reset on real buses (simulators: ``tests.simulated_buses``): a device comes back
in the power state it had before the stop and holds still: enabled before, it is enabled again
with its target where it is (an LA actuator, a DS servo) or at 0 rpm (a ZLAC706 in velocity
mode); off before, it stays off and nothing is sent to it. What the simulators received after
the reset is the evidence, and a refusal of motion while e-stopped names the reset."""

from __future__ import annotations

import json
import time

import pytest

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.can_frame import CanFrame
from tests.conftest import wait_until
from tests.simulated_buses import SimulatedGateway, simulated_gateway

TIMEOUT_S = 5.0


@pytest.fixture(scope="module")
def world():
    with simulated_gateway(margin_ms=10) as world:
        yield world


def ask(world: SimulatedGateway, device: str, fields: dict) -> dict:
    return world.api.command(device, json.dumps(fields).encode()).result(TIMEOUT_S)


def ok(world: SimulatedGateway, device: str, fields: dict) -> dict:
    reply = ask(world, device, fields)
    assert reply["ok"], reply
    return reply


def serial_frames(simulator, since: int) -> list:
    frames = []
    for record in simulator.recorder.received()[since:]:
        decoder = simulator.codec.CommandDecoder()
        decoder.feed(bytes.fromhex(record.wire))
        frames += list(decoder.events())
    return frames


def can_writes(world: SimulatedGateway, since: int) -> list:
    writes = []
    for record in world.can_sim.recorder.received()[since:]:
        identifier, data = record.wire.split("#")
        decoder = zcan.CommandDecoder()
        decoder.feed(CanFrame(int(identifier, 16), bytes.fromhex(data)))
        writes += [f for f in decoder.events() if isinstance(f, zcan.Write)]
    return writes


def marks(world: SimulatedGateway) -> tuple[int, int, int]:
    return tuple(len(s.recorder.received()) for s in (world.la_sim, world.ds_sim, world.can_sim))


def estop(world: SimulatedGateway) -> None:
    for stopped in world.api.stop_every_bus():
        stopped.result(TIMEOUT_S)


def driver(world: SimulatedGateway, device: str):
    return world.api.devices[device][1]


def not_status(frames: list, device_id: int) -> list:
    """The frames to ``device_id`` that are not a poll (status, read)."""
    polls = (la.ReadCommand, ds.Read)
    return [f for f in frames if getattr(f, "device_id", None) == device_id
            and not isinstance(f, polls)
            and not (isinstance(f, la.ControlCommand) and f.code is la.ControlCode.STATUS)]


def test_a_device_enabled_before_is_enabled_again_holding_where_it_is(world):
    ok(world, "la1", {"op": "enable"})
    ok(world, "la1", {"op": "move", "position": 1300})
    wait_until(lambda: abs(driver(world, "la1").status.position_raw - 1300) < 5)
    estop(world)
    refused = ask(world, "la1", {"op": "move", "position": 500})
    assert refused["error"]["code"] == "estopped" and "reset_estop" in refused["error"]["message"]
    la_mark, _, _ = marks(world)
    here = driver(world, "la1").status.position_raw
    reply = ok(world, "la1", {"op": "reset_estop"})
    assert reply["state"]["enabled"] is True and reply["state"]["estopped"] is False
    sent = not_status(serial_frames(world.la_sim, la_mark), 1)
    assert sent == [la.ControlCommand(1, la.ControlCode.ENABLE), la.MoveCommand(1, here, True)]
    assert not_status(serial_frames(world.la_sim, la_mark), 2) == []  # still e-stopped: its own
    assert driver(world, "la2").estopped
    ok(world, "la1", {"op": "move", "position": 1000})  # it takes commands again


def test_every_device_of_the_gateway_is_reset_to_its_own_power_state(world):
    for device in ("la1", "la2", "la3"):  # la2 off before the stop: paused
        ok(world, device, {"op": "enable"})
    ok(world, "la2", {"op": "pause"})
    ok(world, "arm1", {"op": "torque", "on": True})
    ok(world, "arm2", {"op": "torque", "on": False})
    ok(world, "wheel", {"op": "set_mode", "mode": "velocity"})
    ok(world, "wheel", {"op": "enable"})
    ok(world, "wheel", {"op": "velocity", "rpm": 60})
    wait_until(lambda: driver(world, "arm1").measured["position"] is not None)
    estop(world)
    estop(world)  # a second e-stop does not forget what the first one stopped
    la_mark, ds_mark, can_mark = marks(world)
    for reset in world.api.reset_every_bus("operator")[0]:
        reset.result(TIMEOUT_S)
    la_frames = serial_frames(world.la_sim, la_mark)
    ds_frames = serial_frames(world.ds_sim, ds_mark)
    for device_id in (1, 3):
        assert not_status(la_frames, device_id)[0] == la.ControlCommand(device_id,
                                                                         la.ControlCode.ENABLE)
    assert not_status(la_frames, 2) == []  # off before: nothing sent, and it is no longer latched
    assert not driver(world, "la2").estopped and driver(world, "la2").power.value == "paused"
    arm1 = not_status(ds_frames, 1)
    # target (where it is), a move stored there (one from before the gateway may be), torque on
    assert [type(f) for f in arm1] == [ds.Write, ds.RegWrite, ds.Write]
    assert [arm1[0].address, arm1[2].address] == [0x2A, 0x28] and arm1[2].data == b"\x01"
    assert not_status(ds_frames, 2) == [] and not driver(world, "arm2").estopped
    writes = [(w.register, w.value) for w in can_writes(world, can_mark)]
    assert writes[:2] == [(zcan.CanRegister.TARGET_SPEED, 0),  # nothing preset, then enable
                          (zcan.CanRegister.CONTROL_WORD, zcan.ControlWord.ENABLE)]
    assert driver(world, "wheel").machine.settings.enabled
    assert [e for e in world.api.devices] and not any(driver(world, d).estopped
                                                      for d in world.api.devices)


def test_a_device_not_estopped_is_left_as_it_is_and_another_clients_claim_refuses(world):
    la_mark, _, _ = marks(world)
    assert ok(world, "la3", {"op": "reset_estop"})["state"]["estopped"] is False
    assert not_status(serial_frames(world.la_sim, la_mark), 3) == []
    ok(world, "la3", {"op": "claim", "client": "bob"})
    try:
        refused = ask(world, "la3", {"op": "reset_estop", "client": "alice"})
        assert refused["error"]["code"] == "claimed"
    finally:
        ok(world, "la3", {"op": "release", "client": "bob"})


def test_a_reset_of_every_device_leaves_a_device_another_client_claims_to_its_holder(world):
    """A reset of the whole gateway (its key, the dashboard's, the ROS 2 service) brought a
    device another client claimed out of its e-stop, where that client's own reset of the
    device is refused ``claimed``: the holder's control loop found it enabled by a reset it
    never chose. It is not reset, and the event says so; the holder's reset brings it
    back."""
    for device in ("la1", "la3"):
        ok(world, device, {"op": "enable"})
    ok(world, "la3", {"op": "claim", "client": "bob", "ttl_s": 30})
    try:
        estop(world)
        resets, not_reset = world.api.reset_every_bus("alice")
        assert len(resets) == len(world.runners)  # one reset a bus, skipping what it leaves
        for reset in resets:
            reset.result(TIMEOUT_S)
        assert driver(world, "la3").estopped and not driver(world, "la1").estopped
        assert not_reset == ["la3"]
        refused = ask(world, "la3", {"op": "move", "position": 900, "client": "bob"})
        assert refused["error"]["code"] == "estopped"
        reset, kept = world.api.reset_every_bus("bob")
        for future in reset:
            future.result(TIMEOUT_S)
        assert kept == [] and not driver(world, "la3").estopped
    finally:
        ok(world, "la3", {"op": "release", "client": "bob"})


def test_a_move_stored_before_the_estop_is_not_started_by_an_action_after_its_reset(world):
    """A DS servo's move stored for ACTION (a REG WRITE) before the e-stop ran at the first
    ACTION after the reset, sent by any client to any servo of the bus (an audit): the stop
    stores a move to where the servo is in its place, so the ACTION moves nothing."""
    ok(world, "arm1", {"op": "torque", "on": True})
    ok(world, "arm1", {"op": "move", "position": 3000, "time_ms": 100})
    wait_until(lambda: abs((driver(world, "arm1").measured["position"] or 0) - 3000) < 5)
    ok(world, "arm1", {"op": "move", "position": 700, "time_ms": 100, "deferred": True})
    estop(world)
    for stopped in world.api.reset_every_bus("tester")[0]:
        stopped.result(TIMEOUT_S)
    _, ds_mark, _ = marks(world)
    ok(world, "arm2", {"op": "action"})
    wait_until(lambda: any(isinstance(f, ds.Action)
                           for f in serial_frames(world.ds_sim, ds_mark)))
    wait_until(lambda: driver(world, "arm1").telemetry(0.0)["pending_target"] is None)
    assert abs(driver(world, "arm1").telemetry(0.0)["target"] - 3000) < 5  # not 700
    time.sleep(0.3)  # the stored move took 100 ms; then a poll or two
    here = driver(world, "arm1").measured["position"]
    assert abs(here - 3000) < 5, here
