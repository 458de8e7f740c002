"""The DS servo driver: commands to the manual's bytes, replies (encoded and decoded by the codec)
to state and events, follow coalescing, idempotency; then once through the real serial bus
owner against the simulated servo on a pty."""

from __future__ import annotations

import time

import pytest

from busgate.codecs import ds_servo as ds
from busgate.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import OFFLINE_AFTER
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.sim.ds_servo import AMBIENT_C, CURRENT_MA, DsServoDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from tests.published_state import published

OK = ds.ServoStatus(0)
HOT = ds.ServoStatus.TEMPERATURE
OVERLOAD = ds.ServoStatus.OVERLOAD


def driver(device_id: int = 1, period_s: float = 0.02, name: str = "arm") -> DsServoDriver:
    return DsServoDriver(name, device_id, follow_period_s=period_s)


def plan(d: DsServoDriver, text: str) -> list[Request]:
    return d.plan(d.parse(text))


def wire(requests: list[Request]) -> list[str]:
    return [r.wire.hex(" ").upper() for r in requests]


def reply(device_id: int, status: ds.ServoStatus = OK, data: bytes = b"") -> tuple[object, ...]:
    """A status reply as the bus owner hands it over: encoded, then decoded from bytes."""
    decoder = ds.ReplyDecoder()
    decoder.feed(ds.encode(ds.StatusReply(device_id, status, data)))
    return tuple(decoder.events())


def answer(d: DsServoDriver, request: Request, status=OK, data: bytes = b"", now=1.0) -> dict:
    """As the runner does: the servo answered, then its answer is applied."""
    d.heard(now)
    return d.apply(request, reply(request.expected.source_id, status, data), now)


def event_types(d: DsServoDriver) -> list[str]:
    return [e.type for e in d.drain_events()]


# --- plan: the manual's frames (2.3.1-2.3.7; SYNC WRITE with the corrected checksum BA) ----------


@pytest.mark.parametrize(("text", "frame"), [
    ('{"op":"ping"}', "FF FF 01 02 01 FB"),
    ('{"op":"read","address":56,"length":2}', "FF FF 01 04 02 38 02 BE"),
    ('{"op":"move","position":2000,"time_ms":1000,"deferred":true}',
     "FF FF 01 07 04 2A 07 D0 03 E8 07"),
    ('{"op":"action"}', "FF FF FE 02 05 FA"),
    ('{"op":"group_move","targets":[{"id":1,"position":2000,"time_ms":1000},'
     '{"id":3,"position":2000,"time_ms":1000}]}',
     "FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 BA"),
    ('{"op":"reset"}', "FF FF 01 02 06 F6"),
])
def test_plan_gives_the_manuals_frames(text: str, frame: str) -> None:
    assert wire(plan(driver(1), text)) == [frame]


@pytest.mark.parametrize(("text", "idempotent"), [
    ('{"op":"ping"}', True),
    ('{"op":"read","address":56,"length":2}', True),
    ('{"op":"move","position":100}', True),
    ('{"op":"move","position":100,"deferred":true}', True),  # a new REG WRITE replaces the old
    ('{"op":"torque","on":true}', True),
    ('{"op":"goto_preset","n":2}', True),
    ('{"op":"group_move","targets":[{"id":1,"position":5}]}', True),
    ('{"op":"write","address":42,"data":"0064"}', False),
    ('{"op":"set_id","new_id":9}', False),
    ('{"op":"store_preset","n":1}', False),
    ('{"op":"reset"}', False),
    ('{"op":"action"}', False),
])
def test_only_harmless_repeats_are_idempotent(text: str, idempotent: bool) -> None:
    [request] = plan(driver(), text)
    assert request.idempotent is idempotent


def test_plan_changes_no_state_and_refuses_a_pointless_set_id() -> None:
    d = driver(4)
    plan(d, '{"op":"set_id","new_id":9}')
    plan(d, '{"op":"move","position":100}')
    assert d.device_id == 4 and d.telemetry(0)["target"] is None
    with pytest.raises(CommandError, match="already has id 4"):
        plan(d, '{"op":"set_id","new_id":4}')
    with pytest.raises(CommandError):
        d.plan(object())


def test_safe_stop_switches_torque_off() -> None:
    [request] = driver(1).safe_stop()
    assert request.frame == ds.Write(1, 0x28, b"\x00") and request.idempotent
    assert wire([request]) == ["FF FF 01 04 03 28 00 CF"]  # ~(01+04+03+28+00)


def test_safe_stop_replaces_a_stored_move_by_one_to_where_the_servo_is() -> None:
    """A move stored for ACTION before an e-stop ran at the first ACTION after its reset (an
    audit: any client's action on any servo of the bus); the stop stores one to where the
    servo is in its place, once torque is off."""
    d = driver(1)
    answer(d, plan(d, '{"op":"move","position":700,"time_ms":300,"deferred":true}')[0])
    d.measured["position"] = 3500
    torque_off, stored = d.safe_stop()
    assert torque_off.frame == ds.Write(1, 0x28, b"\x00")
    assert stored.frame == ds.RegWrite(1, 3500, 0) and stored.idempotent
    answer(d, stored)
    assert d.telemetry(0)["pending_target"] == 3500
    d.measured["position"] = 3400  # limp, it sagged: the reset stores where it is now
    [move] = plan(d, '{"op":"move","position":3400}')
    assert [r.frame for r in d.hold_still()] == [
        move.frame, ds.RegWrite(1, 3400, 0), ds.Write(1, 0x28, b"\x01")]
    d.measured["position"] = None  # where it is not known, nor its target: nothing to store
    assert len(d.safe_stop()) == 1


def test_a_stored_move_of_a_servo_whose_position_is_not_known_goes_to_its_target() -> None:
    """Its position not known at the stop (no reading yet, or one past its joint's limits),
    the move stored before the stop was left in place, and the first ACTION after the reset
    started it once torque was on again. Its target is what torque on drives it to anyway,
    so a move there is stored in its place; with no target known either, nothing."""
    d = driver(1)
    [move] = plan(d, '{"op":"move","position":2500}')
    answer(d, move)
    answer(d, plan(d, '{"op":"move","position":700,"deferred":true}')[0])
    assert d.measured["position"] is None
    assert [r.frame for r in d.safe_stop()][1:] == [ds.RegWrite(1, 2500, 0)]
    d.target = None
    assert len(d.safe_stop()) == 1


def test_a_move_stored_before_the_driver_was_made_is_replaced_at_the_stop() -> None:
    """A servo keeps a move stored for ACTION while a gateway, or a bus worker, starts anew
    (an audit: a worker killed and started again, its e-stop left the move stored before for
    the first action after the reset). A new driver takes one to be stored until it sees an
    ACTION."""
    d = driver(1)
    d.measured["position"] = 1000
    assert [r.frame for r in d.safe_stop()] == [ds.Write(1, 0x28, b"\x00"), ds.RegWrite(1, 1000, 0)]
    [action] = plan(d, '{"op":"action"}')
    d.apply(action, (), 1.0)
    assert len(d.safe_stop()) == 1


def test_a_stored_move_whose_answer_was_lost_is_replaced_at_the_stop_too() -> None:
    """A REG WRITE unanswered may be stored all the same; an ACTION since starts it."""
    d = driver(1)
    d.measured["position"] = 2000
    [store] = plan(d, '{"op":"move","position":700,"deferred":true}')
    d.missed(1.0, store.frame)
    assert [r.frame for r in d.safe_stop()][1:] == [ds.RegWrite(1, 2000, 0)]
    [action] = plan(d, '{"op":"action"}')
    d.apply(action, (), 1.0)
    assert len(d.safe_stop()) == 1  # started since: nothing stored


# --- poll ----------------------------------------------------------------------------------------


def test_poll_is_two_reads_that_skip_the_write_only_preset_addresses() -> None:
    requests = driver(1).poll()
    assert [(r.frame.address, r.frame.length) for r in requests] == [(0x28, 20), (0x3F, 1)]
    assert all(r.idempotent and r.expected.source_id == 1 for r in requests)
    reads = [(r.frame.address, r.frame.length) for r in requests]
    covered = {a for address, length in reads for a in range(address, address + length)}
    for name in ("current", "present_position", "speed", "temperature", "torque_enable",
                 "target_position"):
        register = ds.REGISTERS[name]
        assert set(range(register.address, register.end)) <= covered
    assert not covered & set(ds.GOTO_PRESET_ADDRESSES)


def _poll_replies(position: int, speed: int, current: int, temperature: int,
                  torque: int = 1, target: int | None = None) -> list[bytes]:
    first = bytearray(20)
    first[0] = torque
    first[0x2A - 0x28 : 0x2C - 0x28] = (position if target is None else target).to_bytes(2, "big")
    first[0x2E - 0x28 : 0x30 - 0x28] = current.to_bytes(2, "big")
    first[0x38 - 0x28 : 0x3A - 0x28] = position.to_bytes(2, "big")
    first[0x3A - 0x28 : 0x3C - 0x28] = speed.to_bytes(2, "big")
    return [bytes(first), bytes([temperature])]


def test_poll_replies_become_telemetry_in_named_units() -> None:
    d = driver(1)
    for request, data in zip(d.poll(), _poll_replies(2047, 12, 250, 31), strict=True):
        answer(d, request, data=data)
    assert published(d, 2.0) | {"ts": None, "last_reply_age_s": None} == {
        "ts": None, "device": "arm", "kind": "ds_servo", "online": True, "last_reply_age_s": None,
        "estopped": False, "position": 2047, "speed_raw": 12, "current_ma": 250,
        "temperature_c": 31, "target": 2047, "pending_target": None, "torque_on": True,
        "enabled": True, "faults": [],
        # Without a joint table: raw units, its current as its effort in A.
        "joint": {"name": "arm", "type": "position", "unit": "raw", "position": 2047.0,
                  "velocity": None, "effort": 0.25, "target": 2047.0},
        "stale": False,
    }


def test_torque_back_on_after_the_gateway_switched_it_off_is_a_reboot() -> None:
    """The power-up value of the torque switch is on: read back on where the gateway had
    switched it off, the servo rebooted. The switch-off is sent again with the next poll,
    and nothing that moves it."""
    d = driver(1)
    for request, data in zip(d.poll(), _poll_replies(100, 0, 0, 30), strict=True):
        answer(d, request, data=data)
    stop, _ = d.safe_stop()  # torque off, and a move stored where the servo is
    answer(d, stop)
    for request, data in zip(d.poll(), _poll_replies(100, 0, 0, 30, torque=0), strict=True):
        answer(d, request, data=data)
    assert not d.restore_pending and "rebooted" not in event_types(d)
    for request, data in zip(d.poll(), _poll_replies(100, 0, 0, 30, torque=1), strict=True):
        answer(d, request, data=data)
    [event] = [e for e in d.drain_events() if e.type == "rebooted"]
    assert event.fields == {"evidence": "torque on again, its power-up value", "restoring": 1}
    assert d.restore_pending and [r.frame for r in d.restore()] == [stop.frame]


def test_a_resets_torque_on_left_unanswered_and_read_back_on_is_no_reboot() -> None:
    """The reset's torque-on write may land though its answer is lost: the torque is then not
    known, and read back on it is as asked, not a reboot whose restore would switch it off
    again (a reboot seen once over bus workers undid a reset so)."""
    d = driver(1)
    for request, data in zip(d.poll(), _poll_replies(100, 0, 0, 30), strict=True):
        answer(d, request, data=data)
    stop, _ = d.safe_stop()  # torque off, and a move stored where the servo is
    answer(d, stop)
    move, stored, torque_on = d.reset_estop()
    answer(d, move)
    answer(d, stored)
    d.missed(1.5, torque_on.frame)
    assert d.telemetry(1.5)["enabled"] is None, "not known until read"
    for request, data in zip(d.poll(), _poll_replies(100, 0, 0, 30, torque=1), strict=True):
        answer(d, request, data=data)
    assert "rebooted" not in event_types(d) and not d.restore_pending
    assert d.telemetry(2.0)["enabled"] is True and d.restore() == []


def test_read_answers_data_and_named_values_and_updates_telemetry() -> None:
    d = driver(1)
    [request] = plan(d, '{"op":"read","address":56,"length":2}')
    assert answer(d, request, data=b"\x07\xff") == {
        "data": "07ff", "values": {"present_position": 2047}}
    assert d.telemetry(1.0)["position"] == 2047


# --- faults and liveness -------------------------------------------------------------------------


def test_each_fault_change_emits_one_event() -> None:
    d = driver(1)
    [ping] = plan(d, '{"op":"ping"}')
    answer(d, ping)
    assert event_types(d) == ["online"]
    answer(d, ping, HOT)
    answer(d, ping, HOT)  # unchanged: no second event
    answer(d, ping, HOT | OVERLOAD)
    answer(d, ping, OVERLOAD)
    events = d.drain_events()
    assert [(e.type, e.fields) for e in events] == [
        ("fault", {"faults": ["temperature"], "raised": ["temperature"], "cleared": []}),
        ("fault", {"faults": ["temperature", "overload"], "raised": ["overload"], "cleared": []}),
        ("fault", {"faults": ["overload"], "raised": [], "cleared": ["temperature"]}),
    ]
    assert d.telemetry(1.0)["faults"] == ["overload"]


def test_any_reply_carries_the_status_byte() -> None:
    d = driver(1)
    [move] = plan(d, '{"op":"move","position":100}')
    answer(d, move, ds.ServoStatus.VOLTAGE)
    assert d.telemetry(1.0)["faults"] == ["voltage"]


def test_offline_after_missed_replies_and_online_again_each_once() -> None:
    d = driver(1)
    [ping] = plan(d, '{"op":"ping"}')
    answer(d, ping, now=1.0)
    for k in range(OFFLINE_AFTER + 2):
        d.missed(2.0 + k)
    assert not d.online
    answer(d, ping, now=9.0)
    assert event_types(d) == ["online", "offline", "online"]


def test_an_unconfirmed_request_changes_nothing() -> None:
    d = driver(1)
    [request] = plan(d, '{"op":"set_id","new_id":9}')
    assert d.apply(request, (), 1.0) == {}
    # Another servo's reply is never handed over: the bus owner matches every reply to its
    # request (tests/test_line_edges.py).
    assert d.device_id == 1 and not d.online and event_types(d) == []


# --- commanded state -------------------------------------------------------------------------


def test_set_id_changes_the_id_once_confirmed() -> None:
    d = driver(1)
    [request] = plan(d, '{"op":"set_id","new_id":9}')
    answer(d, request)  # the servo answers under its old id
    assert d.device_id == 9
    assert [(e.type, e.fields) for e in d.drain_events()][1:] == [
        ("id_changed", {"old_id": 1, "new_id": 9, "reason": "written"})]
    assert d.poll()[0].wire[2] == 9


def test_reset_returns_the_servo_to_the_factory_id_and_forgets_commands() -> None:
    d = driver(5)
    answer(d, plan(d, '{"op":"move","position":300}')[0])
    answer(d, plan(d, '{"op":"reset"}')[0])
    assert d.device_id == ds.REGISTERS["servo_id"].default
    assert d.telemetry(1.0)["target"] is None


def test_targets_and_torque_follow_what_was_confirmed_or_sent() -> None:
    d = driver(3)
    answer(d, plan(d, '{"op":"move","position":300,"time_ms":500}')[0])
    assert d.telemetry(0)["target"] == 300
    answer(d, plan(d, '{"op":"move","position":900,"deferred":true}')[0])
    assert d.telemetry(0)["target"] == 300 and d.telemetry(0)["pending_target"] == 900
    [action] = plan(d, '{"op":"action"}')
    assert action.expected is None
    d.apply(action, (), 1.0)
    assert (d.telemetry(0)["target"], d.telemetry(0)["pending_target"]) == (900, None)
    [group] = plan(d, '{"op":"group_move","targets":[{"id":1,"position":7},{"id":3,"position":8}]}')
    d.apply(group, (), 1.0)
    assert d.telemetry(0)["target"] == 8
    answer(d, plan(d, '{"op":"torque","on":false}')[0])
    assert d.telemetry(0)["torque_on"] is False
    answer(d, plan(d, '{"op":"goto_preset","n":1}')[0])
    assert d.telemetry(0)["target"] is None


# --- follow --------------------------------------------------------------------------------------


def test_follow_target_takes_one_position_and_nothing_else() -> None:
    d = driver()
    assert d.follow_target({"position": 4095}) == 4095
    for bad in ({"position": 4096}, {"position": -1}, {"position": "5"}, {"position": True},
                {"position": 5, "time_ms": 10}, {}, [5]):
        with pytest.raises(CommandError):
            d.follow_target(bad)


def test_follow_request_coalesces_into_one_sync_write_timed_to_the_period() -> None:
    assert DsServoDriver.follow_group_limit == ds.MAX_SYNC_TARGETS
    d1, d3 = driver(1, 0.01), driver(3, 0.01)
    request = DsServoDriver.follow_request([(d1, 2000), (d3, 1000)])
    assert request.expected is None and request.idempotent
    # 2000 and 1000 in 10 ms each (0x000A): the manual's SYNC WRITE layout.
    assert wire([request]) == [ds.encode(ds.SyncWrite((
        ds.SyncTarget(1, 2000, 10), ds.SyncTarget(3, 1000, 10)))).hex(" ").upper()]
    assert request.wire.hex()[:12] == "fffffe0e832a"
    d3.apply(request, (), 1.0)
    assert d3.telemetry(1.0)["target"] == 1000


def test_follow_request_fills_one_frame_and_refuses_more() -> None:
    drivers = [driver(i) for i in range(1, ds.MAX_SYNC_TARGETS + 2)]
    full = DsServoDriver.follow_request([(d, 100) for d in drivers[:-1]])
    assert len(full.frame.targets) == ds.MAX_SYNC_TARGETS
    with pytest.raises(CommandError):
        DsServoDriver.follow_request([(d, 100) for d in drivers])
    with pytest.raises(CommandError):
        DsServoDriver.follow_request([])


# --- end to end: the real serial bus owner against the simulated servo --------------------------

BAUD = 115_200


def test_through_the_bus_owner_and_the_simulator() -> None:
    servo = DsServoDevice(2, position_raw=1000)
    timing = link_timing("ds_servo", BAUD, margin_s=0.05)
    with SerialSimulator(ds, [servo], baudrate=BAUD) as simulator:
        owner = SerialBusOwner(simulator.port, ds, timing, BusCounters(time.perf_counter()))
        owner.open()
        try:
            d = driver(2)

            def run(requests: list[Request]) -> list[dict]:
                results = []
                for request in requests:
                    exchange = owner.exchange(request)
                    if exchange.reply:  # as the runner does: heard, then the answer applied
                        d.heard(exchange.end)
                    results.append(d.apply(request, exchange.reply, exchange.end))
                return results

            run(d.poll())
            state = d.telemetry(0)
            assert (state["position"], state["temperature_c"]) == (1000, AMBIENT_C)
            assert state["current_ma"] == CURRENT_MA["holding"] and d.online
            run(plan(d, '{"op":"move","position":1500,"time_ms":0}'))
            servo.inject_fault("overload", time.perf_counter())
            run(d.poll())
            assert d.telemetry(0)["faults"] == ["overload"]
            assert event_types(d) == ["online", "fault"]
            run(d.safe_stop())
            assert d.telemetry(0)["torque_on"] is False
        finally:
            owner.close()
