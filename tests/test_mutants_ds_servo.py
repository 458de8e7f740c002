"""The DS servo driver, by plain calls (what each op's frame does in the authority's eyes:
``tests/test_frame_effects.py``): what a reboot restores and forgets, a reset's new id,
the polled spans, and what a refusal says."""

from __future__ import annotations

import pytest

from busgate.codecs import ds_servo as ds
from busgate.errors import CommandError
from busgate.gateway.drivers.base import IdChange, Setpoint
from busgate.gateway.drivers.ds_servo import DsServoDriver, frame_setpoints, poll_spans
from busgate.schemas import ds_servo as ds_schema
from busgate.schemas import inspire_la
from busgate.schemas.joints import Joint, JointTable
from tests.test_driver_ds_servo import answer, driver, plan


def test_a_reboot_restores_torque_off_only_while_it_was_switched_off() -> None:
    servo = driver()
    [off] = plan(servo, '{"op":"torque","on":false}')
    answer(servo, off)
    (restored,) = servo.restore()
    assert restored.wire == off.wire and restored.idempotent
    [on] = plan(servo, '{"op":"torque","on":true}')
    answer(servo, on)
    assert servo.restore() == []  # torque on is what a servo powers up with


def test_a_power_up_forgets_the_target_and_has_torque_on() -> None:
    servo = driver()
    assert servo.telemetry(0.0)["torque_on"] is None  # not read yet
    for text in ('{"op":"torque","on":false}', '{"op":"move","position":100}'):
        [request] = plan(servo, text)
        answer(servo, request)
    servo.forget_on_reboot()
    state = servo.telemetry(0.0)
    assert (state["target"], state["pending_target"], state["torque_on"]) == (None, None, True)


def test_a_reset_puts_the_servo_at_the_factory_id_saying_why() -> None:
    servo = driver(7)
    [reset] = plan(servo, '{"op":"reset"}')
    answer(servo, reset)
    (event,) = [e for e in servo.drain_events() if e.type == "id_changed"]
    assert event.fields == {"old_id": 7, "new_id": 1, "reason": "reset"}
    assert servo.device_id == 1 and servo.telemetry(0.0)["torque_on"] is None


def test_a_sync_write_carries_one_to_its_limit_of_servos() -> None:
    one = DsServoDriver.follow_request([(driver(3), 1500)])
    assert isinstance(one.frame, ds.SyncWrite) and [t.device_id for t in one.frame.targets] == [3]
    with pytest.raises(CommandError) as refused:
        DsServoDriver.follow_request([])
    assert str(refused.value) == (
        f"a SYNC WRITE carries 1 to {DsServoDriver.follow_group_limit} servos, not 0")


def test_an_op_of_another_family_is_refused_naming_it() -> None:
    with pytest.raises(CommandError) as refused:
        driver().frames_of(inspire_la.Pause(op="pause"))
    assert str(refused.value) == "ds_servo has no command Pause"


def test_a_poll_reads_across_reserved_addresses_but_not_write_only_ones() -> None:
    # speed (58-59) and temperature (63): the go-to-preset addresses (60-62) lie between
    assert poll_spans(["speed", "temperature"]) == ((58, 2), (63, 1))
    # torque_enable (40) and target_position (42-43): the reserved 41 is read across
    assert poll_spans(["target_position", "torque_enable"]) == ((40, 4),)
    assert poll_spans(["temperature"]) == ((63, 1),)


def test_a_goto_preset_leaves_the_target_unknown_and_another_write_keeps_it() -> None:
    servo = driver()
    for text in ('{"op":"move","position":100}', '{"op":"write","address":48,"data":"00"}'):
        [request] = plan(servo, text)
        answer(servo, request)
    assert servo.telemetry(0.0)["target"] == 100
    [goto] = plan(servo, '{"op":"goto_preset","n":2}')
    answer(servo, goto)
    assert servo.telemetry(0.0)["target"] is None  # the preset's position is on the servo


def test_torque_on_after_an_estop_clears_estopped() -> None:
    servo = driver()
    servo.safe_stop()
    assert servo.estopped is True
    plan(servo, '{"op":"torque","on":true}')
    assert servo.estopped is False


def test_a_servos_part_of_a_group_move_and_its_scan_probe() -> None:
    servo = driver(4)
    assert servo.group_entry(2000, None) == {"id": 4, "position": 2000, "time_ms": 0}
    assert servo.group_entry(2000, 500) == {"id": 4, "position": 2000, "time_ms": 500}
    [ping] = plan(servo, '{"op":"ping"}')
    probe = DsServoDriver.probe(4)
    assert probe.wire == ping.wire and probe.expected == ping.expected


@pytest.mark.parametrize(("text", "given"), [
    ('{"op":"set_id","new_id":9}', [IdChange(3, 9)]),
    ('{"op":"write","address":5,"data":"09"}', [IdChange(3, 9)]),  # the id register, raw
    ('{"op":"reset"}', [IdChange(3, 1)]),  # factory settings: the factory id
    ('{"op":"write","address":6,"data":"09"}', []),
    ('{"op":"move","position":100}', []),
])
def test_the_ids_a_servos_frames_give_it(text, given) -> None:
    """What the authority refuses when another servo of the bus has that id."""
    servo = driver(3)
    assert servo.id_changes(servo.frames_of(servo.parse(text))) == given


def test_a_raw_write_of_the_torque_switch_lets_an_estopped_servo_move_or_stops_it() -> None:
    """As the torque op does: the gateway judges the frames, not the op's name."""
    servo = driver()
    servo.torque_on = True  # driving when the e-stop comes
    servo.safe_stop()
    plan(servo, '{"op":"write","address":48,"data":"01"}')  # another register: no change
    assert servo.estopped and servo.driving_before_estop
    plan(servo, '{"op":"write","address":40,"data":"01"}')
    assert not servo.estopped
    plan(servo, '{"op":"write","address":40,"data":"00"}')
    assert not servo.driving_before_estop  # switched off: a reset leaves it off


@pytest.mark.parametrize(("read", "held"), [(2048, None), (4095, None), (1500, 1500)])
def test_a_reset_holds_only_a_position_within_the_joints_limits(read, held) -> None:
    """A position read beyond the joint's max (2 rad at 0.001 rad a count: raw 2000) is no
    target: the servo stays off (torque on would drive it somewhere); within, it is held."""
    joint = Joint.of("arm", ds_schema.JOINT, JointTable(unit="rad", scale=0.001, max=2.0))
    servo = DsServoDriver("arm", 1, joint=joint)
    [request] = plan(servo, '{"op":"read","address":56,"length":2}')
    answer(servo, request, data=read.to_bytes(2, "big"))
    requests = servo.hold_still()
    if held is None:
        assert requests == [] and not servo.driving()
    else:
        move, stored, torque = requests  # a move stored before the gateway may be: replaced
        assert move.frame.data[:2] == held.to_bytes(2, "big") and torque.frame.data == b"\x01"
        assert stored.frame == ds.RegWrite(1, held, 0)


def test_an_action_or_sync_write_another_sent_is_its_own_too() -> None:
    servo = driver(2)
    [stored] = plan(servo, '{"op":"move","position":2222,"deferred":true}')
    answer(servo, stored)
    servo.moved_by(ds.Ping(1))  # no move: nothing
    assert (servo.pending_target, servo.target) == (2222, None)
    servo.moved_by(ds.Action())
    assert (servo.pending_target, servo.target) == (None, 2222)
    servo.moved_by(ds.SyncWrite((ds.SyncTarget(1, 100, 0), ds.SyncTarget(2, 3300, 0))))
    assert servo.target == 3300


def test_a_write_that_moves_the_centre_and_sets_the_target_sets_no_known_position() -> None:
    """One write from the centre's offset on to the target passed the limits as the target
    alone, where the shaft goes to that target shifted by the new offset."""
    offset, target = (1000).to_bytes(2, "big"), (2048).to_bytes(2, "big")
    spanning = ds.Write(1, 0x14, offset + bytes(0x2A - 0x16) + target)
    assert frame_setpoints(spanning) == [Setpoint(1, "position", None)]
    assert frame_setpoints(ds.Write(1, 0x2A, target)) == [Setpoint(1, "position", 2048)]
