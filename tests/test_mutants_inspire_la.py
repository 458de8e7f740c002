"""The Inspire LA driver, by plain calls (what each op's frame does in the authority's eyes:
``tests/test_frame_effects.py``): what a reboot restores, the temperature limits judged
against what was read since a limit was confirmed, and what a refusal says."""

from __future__ import annotations

import pytest

from busgate.codecs import inspire_la as la
from busgate.errors import CommandError, RefusedError
from busgate.gateway.drivers.base import IdChange
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.schemas import inspire_la as inspire_la_schema
from busgate.schemas.joints import Joint, JointTable
from tests.test_driver_inspire_la import answer, decoded, driver, plan, status


def test_a_reboot_restores_the_estop_only_of_an_estopped_actuator_and_limits_repeatably():
    actuator = driver()
    [limit] = plan(actuator, '{"op":"set_overcurrent","current_ma":1000}')
    answer(actuator, limit, decoded(la.WriteReply(3, 32)))
    (restored,) = actuator.restore()
    assert restored.wire == limit.wire and restored.idempotent
    actuator.safe_stop()
    estop, again = actuator.restore()
    assert estop.wire.hex() == "55aa03030400232d" and again.wire == limit.wire


def test_both_temperatures_restored_go_in_an_order_the_actuator_takes_from_any_pair() -> None:
    """Set 70 °C, rewarm 50, then 58 °C; the reboot brings the actuator's 80 and 60 back, and
    58 written first is out of the pair's range (under 60 + 5): the simulated actuator ignored
    it and stayed at 80 °C while the driver said 58 (outside audit). Read back after the
    restore, the actuator holds what the driver says."""
    actuator, device = driver(), InspireLaDevice(3)

    def run(requests: list, now: float) -> None:
        for request in requests:
            replies = [event for reply in device.handle(request.frame, now)
                       for event in decoded(reply)]
            answer(actuator, request, tuple(replies), now)

    for text in ('{"op":"set_overtemp","temp_c":70}', '{"op":"set_rewarm","temp_c":50}',
                 '{"op":"set_overtemp","temp_c":58}'):
        run(plan(actuator, text), 1.0)
    device.reboot(2.0)
    run(actuator.restore(), 3.0)
    run(actuator.init(), 4.0)  # reads of what the actuator holds now
    assert (actuator.table[la.OVERTEMP_LIMIT], actuator.table[la.REWARM_TEMPERATURE]) == (580, 500)


def test_a_write_of_part_of_a_register_is_refused_and_a_target_never_restored() -> None:
    """One byte of the target (or of a limit) cannot be judged, and once confirmed it held no
    whole register: it was taken for a limit and written again after every reboot, moving
    the actuator. It is refused; a whole target is confirmed and never written again."""
    actuator = driver()
    for index in (0x37, 0x38, 33):  # the target's two bytes, the over-current's high one
        with pytest.raises(CommandError, match=r"bytes at \d+: write them both"):
            plan(actuator, f'{{"op":"write","index":{index},"data":"14"}}')
    [target] = plan(actuator, '{"op":"write","index":55,"data":"8403"}')
    answer(actuator, target, decoded(la.WriteReply(3, 55)))
    assert actuator.restore() == []


def test_a_limit_confirmed_then_read_anew_is_judged_by_what_was_read() -> None:
    actuator = driver()
    [overtemp] = plan(actuator, '{"op":"set_overtemp","temp_c":70.5}')
    answer(actuator, overtemp, decoded(la.WriteReply(3, 98)))
    [read] = plan(actuator, '{"op":"read","index":98,"length":2}')
    answer(actuator, read, decoded(la.ReadReply(3, 98, (800).to_bytes(2, "little"))))
    plan(actuator, '{"op":"set_rewarm","temp_c":74}')  # under 80 °C - 5, as read since


def test_a_temperature_refusal_names_the_actuator_the_register_and_its_value() -> None:
    actuator = driver()
    [overtemp] = plan(actuator, '{"op":"set_overtemp","temp_c":70}')
    answer(actuator, overtemp, decoded(la.WriteReply(3, 98)))
    with pytest.raises(CommandError) as refused:
        plan(actuator, '{"op":"set_rewarm","temp_c":66}')
    assert str(refused.value) == ("rod: overtemp_limit 700 is below rewarm_temperature 660 + "
                                  "50 (limit must be ≥ rewarm + 5 °C)")
    assert (refused.value.field, refused.value.value) == ("overtemp_limit", 700)


def test_what_a_group_or_a_follow_tick_cannot_carry_is_refused_saying_why() -> None:
    actuator = driver()
    with pytest.raises(CommandError) as refused:
        actuator.group_entry(1000, 500)
    assert str(refused.value) == "Inspire LA group moves have no move time; drop time_ms"
    actuator.safe_stop()  # an e-stop that came as a play was checked: refused as any motion
    with pytest.raises(RefusedError) as refused:
        InspireLaDriver.follow_request([(actuator, 1000)])
    assert refused.value.code == "estopped"  # was bad_command, saying only "send enable"
    assert str(refused.value).startswith('rod is e-stopped: send {"op":"reset_estop"}')


def test_holding_still_after_a_reset_targets_where_the_status_last_said() -> None:
    actuator = driver()
    assert [r.wire.hex() for r in actuator.hold_still()] == ["55aa03030400040e"]  # no status
    [query] = plan(actuator, '{"op":"status"}')
    answer(actuator, query, status(position_raw=990))
    enable, here = actuator.hold_still()
    assert enable.wire.hex() == "55aa03030400040e" and here.frame.position_raw == 990


@pytest.mark.parametrize("read", [1601, 2000, -32768])
def test_a_reset_sends_no_target_beyond_the_joints_limits_whatever_was_read(read) -> None:
    """A position read beyond the joint's max (0.008 m: raw 1600), or none the actuator can
    have, is no target: enable alone holds it still (manual 3.5.4); within, it is held."""
    table = JointTable(unit="m", scale=5e-6, max=0.008)
    actuator = InspireLaDriver("rod", 3, joint=Joint.of("rod", inspire_la_schema.JOINT, table))
    [query] = plan(actuator, '{"op":"status"}')
    answer(actuator, query, status(position_raw=read))
    assert [r.wire.hex() for r in actuator.hold_still()] == ["55aa03030400040e"]
    answer(actuator, query, status(position_raw=1600))
    assert actuator.hold_still()[1].frame.position_raw == 1600


@pytest.mark.parametrize("device_id", [1, 3])
def test_a_scan_probes_an_actuator_with_its_status_query(device_id) -> None:
    probe = InspireLaDriver.probe(device_id)
    [query] = plan(driver(device_id), '{"op":"status"}')
    assert probe.wire == query.wire and probe.expected == query.expected


@pytest.mark.parametrize(("text", "given"), [
    ('{"op":"set_id","new_id":9}', [IdChange(3, 9)]),
    ('{"op":"write","index":2,"data":"09"}', [IdChange(3, 9)]),  # the id register, raw
    ('{"op":"write","index":32,"data":"e803"}', []),  # the overcurrent limit
    ('{"op":"move","position":100}', []),
])
def test_the_ids_an_actuators_frames_give_it(text, given) -> None:
    """What the authority refuses when another actuator of the bus has that id."""
    rod = driver(3)
    assert rod.id_changes(rod.frames_of(rod.parse(text))) == given


def test_a_group_frame_another_sent_switches_it_on_unless_estopped() -> None:
    actuator = driver()
    plan(actuator, '{"op":"pause"}')
    group = la.GroupMoveCommand((la.Target(3, 900),))
    actuator.moved_by(group)
    assert actuator.power.value == "on"
    actuator.safe_stop()
    actuator.moved_by(group)  # the authority lets none reach it: nothing said otherwise
    assert actuator.power.value == "estopped"
