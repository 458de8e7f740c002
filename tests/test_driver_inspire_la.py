"""The Inspire LA driver: commands to the manual's bytes, the state rules (e-stop needs enable, the
temperature limits bound each other), replies encoded and decoded by the codec to state and
events, follow coalescing, idempotency; then once through the real serial bus owner against the
simulated actuator on a pty."""

from __future__ import annotations

import time
import typing

import pytest

from busgate.codecs import inspire_la as la
from busgate.errors import CommandError, RefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import OFFLINE_AFTER
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.scheduler.tickers import commanded
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas import inspire_la as schema
from tests.published_state import published

OK = la.Fault(0)


def driver(device_id: int = 3, name: str = "rod") -> InspireLaDriver:
    return InspireLaDriver(name, device_id)


def plan(d: InspireLaDriver, text: str) -> list[Request]:
    return d.plan(d.parse(text))


def hex_of(requests: list[Request]) -> list[str]:
    return [r.wire.hex(" ").upper() for r in requests]


def decoded(frame: object) -> tuple[object, ...]:
    """A reply as the bus owner hands it over: encoded by the codec, then decoded from bytes."""
    decoder = la.ReplyDecoder()
    decoder.feed(la.encode(frame))
    return tuple(decoder.events())


def status(device_id: int = 3, faults: la.Fault = OK, **values: int) -> tuple[object, ...]:
    fields = {"target_raw": 1003, "position_raw": 990, "temperature_c": 20, "current_ma": 100,
              "force_g": 500} | values  # fmt: skip
    return decoded(la.StatusReply(device_id, faults=faults, **fields))


def answer(d: InspireLaDriver, request: Request, reply: tuple[object, ...], now=1.0) -> dict:
    """As the runner does: an answer means the actuator is there, then it is applied."""
    if reply:
        d.heard(now)
    return d.apply(request, reply, now)


def event_types(d: InspireLaDriver) -> list[str]:
    return [e.type for e in d.drain_events()]


# --- plan: the manual's frames, and which may be repeated -------------------------------------

PLANNED = [
    # (command, device id, manual section: frame, idempotent)
    ('{"op":"move","position":1000}', 3, "55 AA 04 03 21 37 E8 03 4A", True),  # 3.7.2
    ('{"op":"move","position":1000,"reply":false}', 3, "55 AA 04 03 03 37 E8 03 2C", True),
    ('{"op":"follow","position":1000}', 3, "55 AA 04 03 20 37 E8 03 49", True),
    # Erratum: the manual prints checksum 28; the bytes sum to 42.
    ('{"op":"follow","position":1000,"reply":false}', 3, "55 AA 04 03 19 37 E8 03 42", True),
    ('{"op":"estop"}', 3, "55 AA 03 03 04 00 23 2D", True),  # 3.7.3
    ('{"op":"enable"}', 3, "55 AA 03 03 04 00 04 0E", True),  # 3.7.4
    ('{"op":"pause"}', 3, "55 AA 03 03 04 00 14 1E", True),
    ('{"op":"save"}', 3, "55 AA 03 03 04 00 20 2A", False),  # 3.7.7
    ('{"op":"status"}', 1, "55 AA 03 01 04 00 22 2A", True),  # 3.7.8
    ('{"op":"clear_fault"}', 1, "55 AA 03 01 04 00 1E 26", True),  # 3.7.9
    ('{"op":"read","index":98,"length":2}', 1, "55 AA 03 01 01 62 02 69", True),  # 3.5.1
    ('{"op":"write","index":55,"data":"1405"}', 1, "55 AA 04 01 02 37 14 05 57", False),  # 3.5.2
    ('{"op":"set_id","new_id":2}', 3, "55 AA 03 03 02 02 02 0C", False),  # 3.7.1
    ('{"op":"set_overtemp","temp_c":70.5}', 3, "55 AA 04 03 02 62 C1 02 2E", True),  # 3.7.5
    ('{"op":"set_rewarm","temp_c":60.5}', 3, "55 AA 04 03 02 64 5D 02 CC", True),  # 3.7.5
    ('{"op":"set_overcurrent","current_ma":1000}', 1, "55 AA 04 01 02 20 E8 03 12", True),  # 3.7.6
    ('{"op":"set_baudrate","baudrate":115200}', 3, "55 AA 03 03 02 0C 02 16", False),
    ('{"op":"zero_force"}', 3, "55 AA 03 03 02 1F 01 28", False),
    ('{"op":"group_move","targets":[{"id":1,"position":1300},{"id":2,"position":1000}]}', 9,
     "55 AA 07 FF F2 01 14 05 02 E8 03 FF", True),
    ('{"op":"group_follow","targets":[{"id":15,"position":2000}]}', 1,
     "55 AA 04 FF F3 0F D0 07 DC", True),
]  # fmt: skip


@pytest.mark.parametrize(("text", "device_id", "frame", "idempotent"), PLANNED)
def test_plan_gives_the_manuals_frames_and_marks_only_harmless_repeats(
    text, device_id, frame, idempotent
):
    [request] = plan(driver(device_id), text)
    assert hex_of([request]) == [frame]
    assert request.idempotent is idempotent


def test_every_op_is_planned():
    models = set(typing.get_args(typing.get_args(schema.Command)[0]))
    assert {type(driver().parse(text)) for text, *_ in PLANNED} == models


def test_poll_is_the_status_query_and_init_also_reads_the_limits():
    d = driver(1)
    [poll] = d.poll()
    assert hex_of([poll]) == ["55 AA 03 01 04 00 22 2A"]
    assert poll.idempotent and poll.expected.wire_bytes == la.STATUS_REPLY_SIZE
    init = d.init()
    assert hex_of(init)[0] == hex_of([poll])[0]
    assert [(r.frame.index, r.frame.length) for r in init[1:]] == [(32, 2), (98, 2), (100, 2)]
    assert all(r.idempotent for r in init)


def test_safe_stop_is_an_estop_to_this_actuator():
    d = driver(3)
    [stop] = d.safe_stop()
    assert hex_of([stop]) == ["55 AA 03 03 04 00 23 2D"] and stop.idempotent
    assert d.telemetry(0)["power"] == "estopped"


# --- state rules: e-stop, enable, pause -------------------------------------------------------

MOTION = [
    '{"op":"move","position":500}',
    '{"op":"follow","position":500,"reply":false}',
    '{"op":"group_move","targets":[{"id":3,"position":500},{"id":4,"position":500}]}',
    '{"op":"group_follow","targets":[{"id":3,"position":500}]}',
]


@pytest.mark.parametrize("stop", ["command", "safe_stop"])
def test_after_an_estop_motion_needs_enable(stop):
    d = driver(3)
    if stop == "command":
        plan(d, '{"op":"estop"}')
    else:
        d.safe_stop()
    assert d.estopped
    for text in MOTION:
        with pytest.raises(RefusedError, match='"enable"') as refused:
            plan(d, text)
        assert refused.value.code == "estopped"
    # What does not move this actuator still goes: status, pause, a group move of others.
    plan(d, '{"op":"status"}')
    plan(d, '{"op":"pause"}')
    plan(d, '{"op":"group_move","targets":[{"id":4,"position":500}]}')
    assert d.telemetry(0)["power"] == "estopped"  # a pause does not undo an e-stop
    plan(d, '{"op":"enable"}')
    for text in MOTION:
        plan(d, text)
    assert d.follow_target({"position": 500}) == 500


def test_pause_needs_no_enable_and_the_next_target_switches_the_stage_on():
    d = driver(3)
    plan(d, '{"op":"pause"}')
    assert d.telemetry(0)["power"] == "paused"
    assert d.follow_target({"position": 10}) == 10
    plan(d, '{"op":"move","position":10}')
    assert d.telemetry(0)["power"] == "on"


# --- state rules: the temperature limits ------------------------------------------------------


def test_temperature_limits_against_the_manuals_defaults():
    d = driver(3)  # 80 °C limit, 60 °C rewarm until read or set
    with pytest.raises(CommandError, match="rewarm"):
        plan(d, '{"op":"set_overtemp","temp_c":64.9}')
    plan(d, '{"op":"set_overtemp","temp_c":65}')
    # A raw write of one register is held to the same rule.
    with pytest.raises(CommandError):
        plan(d, '{"op":"write","index":100,"data":"8b02"}')  # rewarm 65.1 °C


def test_temperature_limits_against_what_was_read():
    d = driver(3)
    [read] = plan(d, '{"op":"read","index":98,"length":4}')
    result = answer(d, read, decoded(la.ReadReply(3, 98, bytes.fromhex("c1025d02"))))
    assert result == {
        "data": "c1025d02",
        "values": {"overtemp_limit": 70.5, "rewarm_temperature": 60.5},
    }
    assert (d.telemetry(0)["overtemp_limit_c"], d.telemetry(0)["rewarm_temperature_c"]) == (
        70.5,
        60.5,
    )
    with pytest.raises(CommandError):
        plan(d, '{"op":"set_rewarm","temp_c":65.6}')
    plan(d, '{"op":"set_rewarm","temp_c":65.5}')


def test_a_planned_limit_counts_until_confirmed_and_a_refusal_changes_nothing():
    d = driver(3)
    [lower] = plan(d, '{"op":"set_overtemp","temp_c":70}')
    # Still unconfirmed: the device may end up at 80 °C or 70 °C; both must hold.
    with pytest.raises(CommandError):
        plan(d, '{"op":"set_rewarm","temp_c":66}')
    assert d.telemetry(0)["overtemp_limit_c"] == 80  # nothing confirmed yet
    answer(d, lower, decoded(la.WriteReply(3, 98)))
    assert d.telemetry(0)["overtemp_limit_c"] == 70
    with pytest.raises(CommandError):
        plan(d, '{"op":"set_rewarm","temp_c":66}')
    plan(d, '{"op":"set_rewarm","temp_c":65}')


def test_a_lost_write_is_superseded_by_the_next_one():
    d = driver(3)
    plan(d, '{"op":"set_overtemp","temp_c":70}')  # never answered
    with pytest.raises(CommandError):
        plan(d, '{"op":"set_rewarm","temp_c":66}')
    plan(d, '{"op":"set_overtemp","temp_c":80}')
    plan(d, '{"op":"set_rewarm","temp_c":66}')


# --- replies to state and events --------------------------------------------------------------


def test_status_replies_become_telemetry_in_named_units():
    d = driver(3)
    assert d.telemetry(0)["position"] is None and d.telemetry(0)["faults"] == []
    [poll] = d.poll()
    assert answer(d, poll, status(3, force_g=-500, position_raw=-20)) == {}
    state = d.telemetry(1.0)
    expected = {"target": 1003, "position": -20, "temperature_c": 20, "current_ma": 100,
                "force_g": -500}  # fmt: skip
    assert {key: state[key] for key in expected} == expected
    assert published(d, 1.5)["online"] and published(d, 1.5)["last_reply_age_s"] == 0.5


@pytest.mark.parametrize("text", [
    '{"op":"move","position":1000}', '{"op":"follow","position":1000}', '{"op":"estop"}',
    '{"op":"set_overcurrent","current_ma":1000}',
])  # fmt: skip
def test_motion_control_and_write_replies_carry_the_status_too(text):
    d = driver(3)
    [request] = plan(d, text)
    answer(d, request, status(3, position_raw=777))
    assert d.telemetry(0)["position"] == 777


def test_both_write_reply_forms_confirm_the_write():
    for reply in (decoded(la.WriteReply(1, 32)), status(1)):
        d = driver(1)
        [request] = plan(d, '{"op":"set_overcurrent","current_ma":1000}')
        assert answer(d, request, reply) == {}
        assert d.telemetry(0)["overcurrent_limit_ma"] == 1000 and d.online


def test_read_values_are_whole_registers_in_their_units():
    d = driver(3)
    [read] = plan(d, '{"op":"read","index":26,"length":8}')  # position, reserved, force zero…
    data = bytes.fromhex("ecff000000 01 dc05")
    result = answer(d, read, decoded(la.ReadReply(3, 26, data)))
    assert result["values"] == {"current_position": -20, "force_zero": 1, "overcurrent_limit": 1500}
    [half] = plan(d, '{"op":"read","index":99,"length":2}')  # half of each temperature
    assert answer(d, half, decoded(la.ReadReply(3, 99, b"\x03\x58")))["values"] == {}


def test_each_fault_change_emits_one_event():
    d = driver(3)
    [poll] = d.poll()
    answer(d, poll, status(3))
    answer(d, poll, status(3, la.Fault.STALL))
    answer(d, poll, status(3, la.Fault.STALL))
    answer(d, poll, status(3, la.Fault.STALL | la.Fault.OVER_TEMPERATURE | la.Fault.MOTOR_FAULT))
    answer(d, poll, status(3, la.Fault.OVER_CURRENT))
    events = d.drain_events()
    assert [e.type for e in events] == ["online", "fault", "fault", "fault"]
    assert [(e.fields["raised"], e.fields["cleared"]) for e in events[1:]] == [
        (["stall"], []),
        (["over_temperature", "motor_fault"], []),
        (["over_current"], ["stall", "over_temperature", "motor_fault"]),
    ]
    assert events[-1].fields["faults"] == ["over_current"] == d.telemetry(0)["faults"]


def test_offline_after_missed_replies_and_online_again_each_once():
    d = driver(3)
    [poll] = d.poll()
    answer(d, poll, status(3), now=1.0)
    for k in range(OFFLINE_AFTER + 2):
        d.missed(2.0 + k)
    assert not d.online
    answer(d, poll, status(3), now=9.0)
    answer(d, poll, status(3), now=9.1)
    assert event_types(d) == ["online", "offline", "online"]


def test_an_unconfirmed_request_changes_nothing():
    d = driver(3)
    [request] = plan(d, '{"op":"set_id","new_id":9}')
    assert answer(d, request, ()) == {}
    # Another actuator's reply is never handed over: the bus owner matches every reply to its
    # request (tests/test_line_edges.py).
    assert d.device_id == 3 and not d.online and event_types(d) == []


@pytest.mark.parametrize("form", ["status", "write"])
def test_set_id_changes_the_id_once_the_reply_confirms(form):
    d = driver(3)
    [request] = plan(d, '{"op":"set_id","new_id":9}')
    assert hex_of(d.poll()) == ["55 AA 03 03 04 00 22 2C"]  # still the old id
    # The actuator takes the new id at once, so its answer may come from either.
    reply = status(9) if form == "status" else decoded(la.WriteReply(9, 2))
    answer(d, request, reply)
    assert d.device_id == 9 and d.poll()[0].frame.device_id == 9
    events = d.drain_events()
    assert events[-1].type == "id_changed" and events[-1].fields == {"old_id": 3, "new_id": 9}


# --- follow -----------------------------------------------------------------------------------


def test_follow_target_takes_one_position_and_nothing_else():
    d = driver(3)
    assert d.follow_target({"position": 2000}) == 2000
    for bad in ({"position": 2001}, {"position": -1}, {"position": "10"}, {"position": 10.0},
                {}, {"position": 10, "reply": True}):  # fmt: skip
        with pytest.raises(CommandError, match="follow target"):
            d.follow_target(bad)


def test_follow_request_for_one_actuator_is_follow_without_reply():
    d = driver(3)
    request = InspireLaDriver.follow_request([(d, 1000)])
    assert hex_of([request]) == ["55 AA 04 03 19 37 E8 03 42"]
    assert request.expected is None and request.idempotent


def test_follow_request_coalesces_into_one_broadcast_frame():
    drivers = [driver(i) for i in (1, 2)]
    request = InspireLaDriver.follow_request([(drivers[0], 1300), (drivers[1], 1000)])
    assert hex_of([request]) == ["55 AA 07 FF F3 01 14 05 02 E8 03 00"]
    assert request.expected is None
    fifteen = [(driver(i), 100 * i) for i in range(1, 16)]
    assert len(InspireLaDriver.follow_request(fifteen).wire) == 51
    with pytest.raises(CommandError, match="15"):
        InspireLaDriver.follow_request([*fifteen, (driver(16), 0)])


def test_follow_request_leaves_out_an_estopped_actuator_and_switches_a_paused_one_on():
    stopped, paused = driver(1), driver(2)
    stopped.safe_stop()
    plan(paused, '{"op":"pause"}')
    request = InspireLaDriver.follow_request([(stopped, 10), (paused, 20)])
    assert request.frame == la.FollowCommand(2, 20, reply=False)
    assert paused.telemetry(0)["power"] == "on"
    with pytest.raises(RefusedError, match="enable"):  # code estopped
        InspireLaDriver.follow_request([(stopped, 10)])


def test_a_stream_starts_from_the_target_last_sent_until_a_status_tells_it_again():
    """A follow frame has no reply: the target it carried is where the next stream starts,
    not the older one the last poll read, which would make its first tick a jump back (an
    audit: a stream took la1 to 1560, the next one's first tick sent 1160). A status answered
    after it says the actuator's own target, as new as any sent before it."""
    d, other = driver(3), driver(4)
    answer(d, d.poll()[0], status(target_raw=1160))
    assert commanded(d, 1.0) == 1160
    tick = InspireLaDriver.follow_request([(d, 1560)])
    answer(d, tick, ())  # went; nobody answers it
    assert commanded(d, 1.1) == 1560, "from the tick's target, not the poll's"
    assert d.telemetry(1.1)["target"] == 1160, "its telemetry says what was read"
    group = InspireLaDriver.follow_request([(other, 500), (d, 1500)])
    answer(other, group, ())  # the broadcast frame, as each device it carried is told
    answer(d, group, ())
    assert (commanded(d, 1.2), commanded(other, 1.2)) == (1500, 500)
    answer(d, plan(d, '{"op":"move","position":900,"reply":false}')[0], ())
    assert commanded(d, 1.3) == 900
    d.moved_by(la.GroupMoveCommand((la.Target(3, 800), la.Target(4, 700))))  # another's
    assert commanded(d, 1.4) == 800
    answer(d, d.poll()[0], status(target_raw=780))  # whatever it says is newer (a frame lost)
    assert commanded(d, 1.5) == 780


# --- end to end: the real serial bus owner against the simulated actuator -----------------------

BAUD = 921_600


def test_through_the_bus_owner_and_the_simulator():
    device = InspireLaDevice(5)
    timing = link_timing("inspire_la", BAUD, margin_s=0.05, gap_s=0.001)
    with SerialSimulator(la, [device], baudrate=BAUD) as simulator:
        owner = SerialBusOwner(simulator.port, la, timing, BusCounters(time.perf_counter()))
        owner.open()
        try:
            d = driver(5)

            def run(requests: list[Request]) -> list[dict]:
                results = []
                for request in requests:
                    exchange = owner.exchange(request)
                    results.append(answer(d, request, exchange.reply, exchange.end))
                    time.sleep(timing.gap_s)
                return results

            results = run(d.init())
            assert results[2]["values"] == {"overtemp_limit": 80.0}
            assert d.telemetry(0)["position"] == 0 and d.online
            run(plan(d, '{"op":"set_overtemp","temp_c":70.5}'))
            assert d.telemetry(0)["overtemp_limit_c"] == 70.5
            run(plan(d, '{"op":"move","position":2000}'))
            device.inject_fault("stall", time.perf_counter())
            run(d.poll())
            assert d.telemetry(0)["faults"] == ["stall"]
            assert event_types(d) == ["online", "fault"]
            run(d.safe_stop())
            with pytest.raises(RefusedError, match="enable"):
                plan(d, '{"op":"move","position":0}')
            run(plan(d, '{"op":"set_id","new_id":6}'))
            assert d.device_id == 6 == device.device_id
            run(d.poll())
            assert d.telemetry(0)["target"] == device.status(time.perf_counter()).target_raw
        finally:
            owner.close()
