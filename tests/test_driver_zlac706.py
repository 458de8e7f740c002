"""The ZLAC706 drivers (CAN and RS232), by plain calls: frames against the manual's bytes, the
order rules, state from acknowledged writes, heartbeats and monitor replies, fault and
online/offline events once each, keep-alive, follow stream, safe stop and idempotency."""

from __future__ import annotations

import math
import time
from collections import deque

import can
import pytest

from busgate.codecs import zlac706_can as can_codec
from busgate.codecs import zlac706_rs232 as rs_codec
from busgate.codecs.can_frame import CanFrame
from busgate.errors import CommandError, DeviceRefusedError, RefusedError
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Effect
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver
from busgate.gateway.drivers.zlac706_state import Mode, Role, Settings
from busgate.gateway.scheduler.devices import tell_unsent
from busgate.gateway.scheduler.planner import Job
from busgate.gateway.sim import zlac706 as sim
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas import zlac706 as zlac_schema
from busgate.schemas.joints import Joint, JointTable

TURN = 2 * math.pi

MANUAL_MONITOR = "80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e e80000e8 e9271020"


def can_driver(heartbeat_ms: int = 0) -> Zlac706CanDriver:
    return Zlac706CanDriver("wheel", 1, heartbeat_ms=heartbeat_ms)


def rs_driver() -> Zlac706Rs232Driver:
    return Zlac706Rs232Driver("wheel", 1)


def plan(driver, text: str) -> list[Request]:
    return driver.plan(driver.parse(text))


def wire(requests: list[Request]) -> list[str]:
    return [str(r.wire) if isinstance(r.wire, CanFrame) else r.wire.hex() for r in requests]


def can_events(data: str, node: int = 1) -> tuple[object, ...]:
    decoder = can_codec.ReplyDecoder()
    decoder.feed(CanFrame(node, bytes.fromhex(data)))
    return tuple(decoder.events())


def rs_events(data: str) -> tuple[object, ...]:
    decoder = rs_codec.ReplyDecoder()
    decoder.feed(bytes.fromhex(data))
    return tuple(decoder.events())


def reply_to(request: Request) -> tuple[object, ...]:
    """The device's answer, encoded by the codec and decoded back as the host sees it."""
    frame = request.frame
    if isinstance(frame, can_codec.Write):
        echo = can_codec.WriteAck(frame.device_id, frame.register, frame.value)
        return can_events(can_codec.encode(echo).data.hex())
    return rs_events(rs_codec.encode(rs_codec.Ack(frame.register)).hex())


def run(driver, requests: list[Request], now: float = 0.0) -> None:
    """As the runner does: the device answered, then its answer is applied."""
    for request in requests:
        driver.went(request.frame)
        driver.heard(now)
        driver.apply(request, reply_to(request), now)


def event_types(driver) -> list[str]:
    return [event.type for event in driver.drain_events()]


def test_settings_fields_are_the_tracked_roles() -> None:
    untracked = {Role.ONE_SHOT, Role.ALARM_RESET, Role.SETTING}
    tracked = {r.value for r in Role if r not in untracked}
    # the enable's run signal too, and where the position targets send the shaft
    assert set(Settings.__dataclass_fields__) == tracked | {"run_signal", "place"}


# --- CAN: frames and order -----------------------------------------------------------------------


def test_can_position_sequence_gives_the_manuals_frames() -> None:
    """Manual 8.1.2 part 3, steps 1-6, acknowledged one by one."""
    d = can_driver()
    steps = [
        ('{"op":"set_mode","mode":"position"}', "001#00fa00190000003f"),
        ('{"op":"set_position_ramp","accel_ms":1000,"decel_ms":1000}', "001#00fa001200000a0a"),
        ('{"op":"set_max_speed","rpm":100}', "001#00fa001400000111"),
        ('{"op":"set_position_mode","relative":true}', "001#00fa00170000005f"),
        ('{"op":"enable"}', "001#00fa00100000001f"),
        ('{"op":"move","position":123456}', "001#00fa00160001e240"),
        ('{"op":"move","position":-123456}', "001#00fa0016fffe1dc0"),
    ]
    for text, frame in steps:
        requests = plan(d, text)
        assert wire(requests) == [frame], text
        run(d, requests)
    state = d.telemetry(0)
    assert (state["mode"], state["enabled"], state["position_mode"]) == ("position", True,
                                                                       "relative")
    # Two steps in relative mode: where they end is not known here, and no step is a place
    # (the target read as one would have been -123456, where the shaft was back at 0).
    assert state["target"] is None
    assert state["position_ramp"] == {"accel_ms": 1000, "decel_ms": 1000}
    assert state["max_speed_rpm"] == pytest.approx(100, abs=0.5)


def test_move_before_enable_is_refused_with_the_reason() -> None:
    d = can_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"position"}'))
    with pytest.raises(CommandError, match=r"before enable.*ignores"):
        plan(d, '{"op":"move","position":10}')
    run(d, plan(d, '{"op":"enable"}'))
    run(d, plan(d, '{"op":"disable"}'))
    with pytest.raises(CommandError, match="enable first"):
        plan(d, '{"op":"move","position":10}')


@pytest.mark.parametrize(
    ("mode", "text"),
    [
        ("position", '{"op":"velocity","rpm":100}'),
        ("torque", '{"op":"velocity","rpm":0}'),
        ("velocity", '{"op":"torque","current_a":1.6}'),
        ("velocity", '{"op":"move","position":1}'),
        (None, '{"op":"velocity","rpm":100}'),
    ],
)
def test_a_target_of_another_mode_is_refused(mode: str | None, text: str) -> None:
    d = can_driver()
    if mode:
        run(d, plan(d, f'{{"op":"set_mode","mode":"{mode}"}}'))
        run(d, plan(d, '{"op":"enable"}'))
    with pytest.raises(CommandError, match=r"needs .* mode"):
        plan(d, text)


def test_speed_and_torque_may_be_preset_before_enable() -> None:
    """The manual's speed and torque sequences set the target before enable."""
    for mode, text in (("velocity", '{"op":"velocity","rpm":500}'),
                       ("torque", '{"op":"torque","current_a":8}')):
        d = can_driver()
        run(d, plan(d, f'{{"op":"set_mode","mode":"{mode}"}}'))
        run(d, plan(d, text))
    assert wire(plan(d, '{"op":"torque","current_a":8}')) == ["001#00fa0008000009c4"]


def test_mode_is_not_changed_while_enabled() -> None:
    d = can_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'))
    run(d, plan(d, '{"op":"enable"}'))
    with pytest.raises(CommandError, match="disable first"):
        plan(d, '{"op":"set_mode","mode":"position"}')
    assert len(plan(d, '{"op":"set_mode","mode":"velocity"}')) == 1  # the same mode is fine


def test_queued_writes_count_until_one_goes_unanswered() -> None:
    """enable then move back to back is right (same device, in order); after a miss it is not."""
    d = can_driver()
    plan(d, '{"op":"set_mode","mode":"position"}')
    plan(d, '{"op":"enable"}')
    assert wire(plan(d, '{"op":"move","position":5}')) == ["001#00fa001600000005"]
    assert d.machine.settings.mode is None  # nothing acknowledged yet
    d.missed(0.0)
    with pytest.raises(CommandError):
        plan(d, '{"op":"move","position":5}')


@pytest.mark.parametrize(
    ("setup", "text", "idempotent"),
    [
        ([], '{"op":"set_mode","mode":"position"}', True),
        ([], '{"op":"enable"}', True),
        ([], '{"op":"disable"}', True),
        ([], '{"op":"set_velocity_ramp","accel_ms":1000,"decel_ms":1100}', True),
        ([], '{"op":"set_gain","gain":"position_kf","value":1}', True),
        ([], '{"op":"set_rated_current","current_ma":8000}', True),
        ([], '{"op":"home"}', False),
        (['{"op":"set_position_mode","relative":false}'], '{"op":"move","position":9}', True),
        (['{"op":"set_position_mode","relative":true}'], '{"op":"move","position":9}', False),
        ([], '{"op":"move","position":9}', False),  # position mode unknown: maybe relative
    ],
)
def test_only_harmless_repeats_are_idempotent(setup, text, idempotent) -> None:
    d = can_driver()
    for step in ['{"op":"set_mode","mode":"position"}', *setup, '{"op":"enable"}']:
        run(d, plan(d, step))
    assert [r.idempotent for r in plan(d, text)] == [idempotent]


@pytest.mark.parametrize("make", [can_driver, rs_driver])
def test_an_alarm_reset_goes_only_with_the_run_signal_cut(make) -> None:
    """The manual's safety notes: an alarm reset with the run signal on starts the drive
    again suddenly. With the enable on, or not known to be off, it is refused; after a
    disable (even one still queued) it goes, once, never repeated after a lost answer, and
    as a setting: it moves nothing then, so an e-stopped drive may take it."""
    d = make()
    with pytest.raises(CommandError, match=r"perhaps on \(not known\): the manual"):
        plan(d, '{"op":"clear_alarm"}')
    run(d, plan(d, '{"op":"enable"}'))
    with pytest.raises(CommandError, match=r"run signal \(its enable\) is on: .* disable first"):
        plan(d, '{"op":"clear_alarm"}')
    plan(d, '{"op":"disable"}')  # queued, not yet acknowledged: the reset goes after it
    (reset,) = plan(d, '{"op":"clear_alarm"}')
    assert not reset.idempotent and d.effect(reset.frame) is Effect.SETTING


def test_an_rs232_drive_in_alarm_has_stopped_but_its_run_signal_is_still_on() -> None:
    """A fault stops the motor (the monitor's running bit clears) with the enable still on:
    the motor reads off, yet an alarm reset would start it again, so it is refused until a
    disable cuts the signal."""
    d = rs_driver()
    run(d, plan(d, '{"op":"enable"}'))
    (monitor,) = d.poll()
    d.apply(monitor, rs_events(MANUAL_MONITOR.replace("80000181", "80000080")), 0.0)
    assert d.telemetry(0.0)["enabled"] is False
    with pytest.raises(CommandError, match="run signal"):
        plan(d, '{"op":"clear_alarm"}')
    run(d, plan(d, '{"op":"disable"}'))
    assert wire(plan(d, '{"op":"clear_alarm"}'))


def test_monitor_is_refused_on_can() -> None:
    with pytest.raises(CommandError, match="RS232"):
        plan(can_driver(), '{"op":"monitor"}')


# --- CAN: keep-alive, stop, follow -------------------------------------------------------------


def velocity_driver(driver, rpm: int = 500):
    run(driver, plan(driver, '{"op":"set_mode","mode":"velocity"}'))
    run(driver, plan(driver, f'{{"op":"velocity","rpm":{rpm}}}'))
    return driver


def test_can_keepalive_repeats_the_speed_while_enabled_and_non_zero() -> None:
    d = velocity_driver(can_driver())
    assert d.keepalive(0.0) is None  # preset, not enabled: nothing turns
    run(d, plan(d, '{"op":"enable"}'))
    period, request = d.keepalive(1.0)
    assert period == 0.4 and request.idempotent
    assert wire([request]) == ["001#00fa001100000555"]  # manual: 500 rpm
    run(d, plan(d, '{"op":"velocity","rpm":0}'))
    assert d.keepalive(2.0) is None
    run(d, plan(d, '{"op":"velocity","rpm":-1000}'))
    assert wire([d.keepalive(3.0)[1]]) == ["001#00fa0011fffff556"]
    run(d, plan(d, '{"op":"disable"}'))
    assert d.keepalive(4.0) is None


def test_can_keepalive_repeats_the_last_speed_written_even_when_its_ack_is_late() -> None:
    """A follow tick's stop whose ack came too late (missed) must not let the keep-alive bring
    back the speed before it: it repeats the stop until the drive has taken it."""
    d = velocity_driver(can_driver())
    run(d, plan(d, '{"op":"enable"}'))
    stop = Zlac706CanDriver.follow_request([(d, 0.0)])
    d.went(stop.frame)
    d.missed(1.0, stop.frame)  # its ack never came in time
    assert d.telemetry(0)["target_speed_rpm"] == pytest.approx(500, abs=0.4)  # acknowledged
    assert wire([d.keepalive(1.5)[1]]) == wire([stop]) == ["001#00fa001100000000"]
    run(d, [stop])  # now taken: nothing turns, nothing to keep alive
    assert d.keepalive(2.0) is None
    faster = Zlac706CanDriver.follow_request([(d, 600.0)])  # a tick, its ack lost too
    d.went(faster.frame)
    d.missed(2.2, faster.frame)
    assert wire([d.keepalive(2.5)[1]]) == wire([faster])


def test_a_stale_streams_stop_is_what_the_keepalive_repeats_until_its_ack() -> None:
    """The 0 rpm a stale stream (or an e-stop) sends is built with the driver, yet counts as
    the last speed written when it goes: while its ack is late, the keep-alive repeats the
    stop, never the speed before it."""
    d = velocity_driver(can_driver())
    run(d, plan(d, '{"op":"enable"}'))
    stop = d.stale_stream()
    assert wire(stop) == ["001#00fa001100000000"] and stop == d.stale_stream()
    d.went(stop[0].frame)
    d.missed(1.0, stop[0].frame)  # its ack never came in time
    assert wire([d.keepalive(1.5)[1]]) == wire(stop)


def test_safe_stop_zeroes_the_speed_then_releases() -> None:
    d = velocity_driver(can_driver())
    run(d, plan(d, '{"op":"enable"}'))
    stop = d.safe_stop()
    assert wire(stop) == ["001#00fa001100000000", "001#00fa00100000000f"]
    assert all(r.idempotent for r in stop)
    run(d, stop)
    assert d.keepalive(0.0) is None and d.telemetry(0)["enabled"] is False


def test_safe_stop_in_position_mode_only_releases_and_drops_queued_outlook() -> None:
    d = can_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"position"}'))
    plan(d, '{"op":"enable"}')  # queued, then voided by the e-stop
    assert wire(d.safe_stop()) == ["001#00fa00100000000f"]
    with pytest.raises(CommandError, match="enable first"):
        plan(d, '{"op":"move","position":1}')


def test_stale_stream_sends_zero_rpm() -> None:
    d = velocity_driver(can_driver())
    assert wire(d.stale_stream()) == ["001#00fa001100000000"]


def test_follow_takes_speeds_in_velocity_mode_only() -> None:
    d = can_driver()
    with pytest.raises(CommandError, match="velocity mode"):
        d.follow_target({"rpm": 100})
    velocity_driver(d)
    assert d.follows == "velocity"
    with pytest.raises(CommandError, match="needs position mode"):
        d.follow_target({"position": 100})
    with pytest.raises(CommandError, match="invalid follow target"):
        d.follow_target({"rpm": 1001})
    with pytest.raises(CommandError, match="rpm or position, one of them"):
        d.follow_target({"rpm": 100, "position": 100})
    target = d.follow_target({"rpm": 100})
    request = Zlac706CanDriver.follow_request([(d, target)])
    assert wire([request]) == ["001#00fa001100000111"] and request.idempotent
    with pytest.raises(CommandError, match="one device"):
        Zlac706CanDriver.follow_request([(d, target), (can_driver(), target)])


def position_driver(driver, *commands: str):
    for command in ('{"op":"set_mode","mode":"position"}', *commands):
        run(driver, plan(driver, command))
    return driver


def test_relative_steps_are_judged_from_where_the_steps_before_send_the_shaft() -> None:
    """An audit: two steps of 6000 pulses sent back to back, each judged from the position
    measured (the shaft had not moved yet), were both within a joint's max of 10000; the
    drive adds each to its last target and stopped at 12000. Judged from where the steps
    before send the shaft as well, the second is refused."""
    joint = Joint.of("wheel", zlac_schema.JOINT, JointTable(
        unit="rad", scale=TURN / 10_000, type="position", min=-TURN, max=TURN))
    d = Zlac706CanDriver("wheel", 1, joint=joint)
    d = position_driver(d, '{"op":"disable"}', '{"op":"set_position_mode","relative":true}',
                        '{"op":"enable"}')  # enabled from off: its zero, and its target, here
    d.take_position(0, 0.0)
    plan(d, '{"op":"move","position":6000}')  # queued, not yet answered
    steps = d.setpoints(d.frames_of(d.parse('{"op":"move","position":6000}')))
    assert sorted(s.value for s in steps if s.quantity == "position") == [6000, 12_000]
    with pytest.raises(RefusedError, match="max"):  # as the bus judges each (``check_limits``)
        for step in steps:
            joint.check(step.quantity, step.value)
    d.take_position(5000, 0.0)  # on its way: from the place it goes to, and from where it is
    steps = d.setpoints(d.frames_of(d.parse('{"op":"move","position":-2000}')))
    assert sorted(s.value for s in steps if s.quantity == "position") == [3000, 4000]
    d.missed(1.0, plan(d, '{"op":"move","position":100}')[0].frame)  # landed, or not
    steps = d.setpoints(d.frames_of(d.parse('{"op":"move","position":100}')))
    assert [s.value for s in steps if s.quantity == "position"] == [5100]  # the place not known
    # An enable queued with a step: the enable's zero is the step's base, as the drive's is
    # (a review: judged from the place before the enable, the outlook kept 11000 for good)
    run(d, plan(d, '{"op":"move","position":2000}'))
    run(d, plan(d, '{"op":"disable"}'))
    requests = plan(d, '{"op":"enable"}') + plan(d, '{"op":"move","position":3000}')
    run(d, requests)
    assert (d.machine.settings.place, d.machine.expected().place) == (3000, 3000)
    steps = d.setpoints(d.frames_of(d.parse('{"op":"move","position":5000}')))
    assert sorted(s.value for s in steps if s.quantity == "position") == [5000, 8000]  # not 16000


def test_follow_takes_positions_in_absolute_position_mode_once_enabled() -> None:
    """The manual: in position mode a target is taken once the motor is enabled, and a
    relative target moves it on by that much (a stream's every tick would)."""
    d = position_driver(can_driver(), '{"op":"set_position_mode","relative":false}')
    with pytest.raises(CommandError, match="enable first"):
        d.follow_target({"position": 5000})
    plan(d, '{"op":"enable"}')  # queued, not yet acknowledged: judged as it will be
    assert d.follows == "position"
    with pytest.raises(CommandError, match="needs velocity mode"):
        d.follow_target({"rpm": 100})
    with pytest.raises(CommandError, match="where the drive holds, which is not known now"):
        d.follow_target({"position": -5000})  # a stream would start from nowhere known
    d.unsolicited(can_events("00fe0020000003e8")[0], 0.0)  # a heartbeat: at 1000
    target = d.follow_target({"position": -5000})
    assert target == -5000
    request = Zlac706CanDriver.follow_request([(d, target)])
    assert wire([request]) == ["001#00fa0016ffffec78"] and request.idempotent  # register 16
    run(d, plan(d, '{"op":"set_position_mode","relative":true}'))
    assert d.follows is None  # nothing it could stream: a rpm is refused by its mode
    with pytest.raises(CommandError, match="the position mode is relative"):
        d.follow_target({"position": 5000})
    unknown = position_driver(can_driver(), '{"op":"enable"}')
    with pytest.raises(CommandError, match="the position mode is not known"):
        unknown.follow_target({"position": 5000})


def test_rs232_follow_streams_no_positions() -> None:
    """RS232 writes a position in two frames (high half, then low): a tick is one frame."""
    d = position_driver(rs_driver(), '{"op":"set_position_mode","relative":false}',
                        '{"op":"enable"}')
    assert d.follows is None
    with pytest.raises(CommandError, match="two frames"):
        d.follow_target({"position": 5000})


def test_a_worker_s_position_mode_is_mirrored() -> None:
    """The main process judges follow targets by what the worker's driver told: its mode,
    its position mode, whether it is enabled, and where it holds."""
    d = can_driver()
    d.mirror({"mode": "position", "position_mode": "absolute", "enabled": True,
              "target": None, "position": None})
    with pytest.raises(CommandError, match="not known now"):
        d.follow_target({"position": 7})
    d.mirror({"target": 0, "position": None})  # it holds at its target
    assert d.follow_target({"position": 7}) == 7
    d.mirror({"target": None, "position": 3})  # it is where it was read
    assert d.follow_target({"position": 7}) == 7 and d.follows == "position"
    d.mirror({"position_mode": "relative"})
    with pytest.raises(CommandError, match="relative"):
        d.follow_target({"position": 7})
    d.mirror({"position_mode": None})  # a state that does not say leaves it as it was
    assert d.follows is None


def test_a_followed_speed_is_kept_alive_once_acknowledged() -> None:
    d = velocity_driver(can_driver(), rpm=0)
    run(d, plan(d, '{"op":"enable"}'))
    run(d, [Zlac706CanDriver.follow_request([(d, d.follow_target({"rpm": 100}))])])
    assert wire([d.keepalive(0.0)[1]]) == ["001#00fa001100000111"]


# --- CAN: init, heartbeats, alarms, liveness -----------------------------------------------------


def test_can_poll_is_empty_and_init_writes_something_harmless() -> None:
    d = can_driver()
    assert d.poll() == []
    # mode unknown: 0 rpm and 0 A (no speed or torque preset left to start it at an enable),
    # then release
    assert wire(d.init()) == ["001#00fa001100000000", "001#00fa000800000000",
                              "001#00fa00100000000f"]
    run(d, plan(d, '{"op":"enable"}'))
    assert d.init() == []  # a client enabled it since: init must not release it again
    run(d, plan(d, '{"op":"disable"}'))
    run(d, plan(d, '{"op":"set_mode","mode":"torque"}'))
    assert wire(d.init()) == ["001#00fa00190000008f"]  # mode known: written again


def test_can_init_releases_a_motor_whose_mode_is_known_and_power_stage_is_not() -> None:
    """A base sets its wheels' velocity mode as they come online, which can be before their
    first init: the init, seeing the mode known, only wrote it again, and a speed preset
    before the gateway came started the motor at the next enable of the wheel (an audit saw
    the demo's wheels never released)."""
    d = can_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'))
    assert wire(d.init()) == ["001#00fa00190000002f", "001#00fa001100000000",
                              "001#00fa00100000000f"]  # the mode, 0 rpm (no torque there), off


def test_a_disable_leaves_no_speed_preset_for_the_next_enable() -> None:
    """The manual: a speed preset starts the motor the moment it is enabled. A speed written
    before a disable must not: the disable writes 0 rpm first (and the keep-alive forgets the
    speed), while a preset written after it is the client's, and stays."""
    d = velocity_driver(can_driver(), rpm=50)
    run(d, plan(d, '{"op":"enable"}'))
    assert wire(plan(d, '{"op":"disable"}')) == ["001#00fa001100000000", "001#00fa00100000000f"]
    run(d, plan(d, '{"op":"disable"}'))
    run(d, plan(d, '{"op":"enable"}'))
    assert d.keepalive(1.0) is None and d.telemetry(0)["target_speed_rpm"] == 0
    run(d, plan(d, '{"op":"disable"}'))
    run(d, plan(d, '{"op":"velocity","rpm":100}'))  # preset after the disable
    assert wire(plan(d, '{"op":"enable"}')) == ["001#00fa00100000001f"]


@pytest.mark.parametrize(("driver", "zero_torque", "release"), [
    (can_driver, "001#00fa000800000000", "001#00fa00100000000f"),
    (rs_driver, "08000008", "00000000"),
])
def test_in_torque_mode_a_stop_or_disable_leaves_no_torque_for_the_next_enable(
        driver, zero_torque, release) -> None:
    """The manual (8.1.2 step 6, 8.2.1 note 12): enabled in torque mode, the motor turns at
    the torque set. An e-stop and a disable write 0 A before the release, so that the reset's
    enable (or a client's) drives nothing until a new torque is sent."""
    d = driver()
    run(d, plan(d, '{"op":"set_mode","mode":"torque"}'))
    run(d, plan(d, '{"op":"torque","current_a":2.0}'))
    run(d, plan(d, '{"op":"enable"}'))
    stop = d.safe_stop()
    assert wire(stop) == [zero_torque, release]
    run(d, stop)
    assert d.telemetry(0)["target_current_a"] == 0.0
    assert wire(d.reset_estop()) == wire(plan(driver(), '{"op":"enable"}'))
    run(d, plan(d, '{"op":"torque","current_a":1.5}'))
    assert wire(plan(d, '{"op":"disable"}')) == [zero_torque, release]


def test_without_heartbeats_state_carries_the_commanded_and_online_follows_acks() -> None:
    d = velocity_driver(can_driver())
    state = d.telemetry(0)
    assert state["measured"] is False and state["position"] is None
    assert state["target_speed_rpm"] == pytest.approx(500, abs=0.5)
    assert d.online and event_types(d) == ["online"]
    for _ in range(3):
        d.missed(1.0)
    d.check_heartbeat(100.0)  # none expected: never "lost"
    assert not d.online and [e.fields for e in d.drain_events()] == [{"reason": "no reply"}]


def test_heartbeats_give_measured_values_and_their_loss_marks_offline_once() -> None:
    d = can_driver(heartbeat_ms=100)
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'), now=0.0)
    assert not d.online  # an acknowledged write alone: heartbeats expected, none yet
    d.unsolicited(can_events("00fe00200001e1e2")[0], 1.0)  # manual: position 123362
    d.unsolicited(can_events("00fe0021001e043f")[0], 1.0)  # manual: 0.30 A, 398 rpm
    state = d.telemetry(1.0)
    assert state["measured"] is True and state["position"] == 123362
    assert state["current_ma"] == 300 and state["speed_rpm"] == pytest.approx(398.1, abs=0.1)
    d.check_heartbeat(1.3)
    assert d.online and event_types(d) == ["online"]
    d.check_heartbeat(1.31)
    d.check_heartbeat(2.0)
    assert not d.online and [e.fields for e in d.drain_events()] == [
        {"reason": "heartbeat lost"}]
    d.unsolicited(can_events("00fe00200001e1e2")[0], 2.1)
    assert d.online and event_types(d) == ["online"]


def test_a_node_that_heartbeats_but_answers_no_write_goes_offline_until_it_answers() -> None:
    """A heartbeat shows the node reports, not that it takes writes (rule 2): it neither
    clears the count of unanswered writes nor brings back a node that answered none of three
    in a row; an answered write does, and the next heartbeat brings the node online."""
    d = can_driver(heartbeat_ms=100)
    position = can_events("00fe00200001e1e2")[0]
    d.unsolicited(position, 0.0)
    assert d.online and event_types(d) == ["online"]
    for moment in (0.1, 0.2, 0.3):
        d.missed(moment)
        d.unsolicited(position, moment + 0.05)
    assert not d.online and [e.fields for e in d.drain_events()] == [{"reason": "no reply"}]
    d.unsolicited(position, 0.4)
    assert not d.online and event_types(d) == []
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'), now=0.5)  # an answered write
    d.unsolicited(position, 0.6)
    assert d.online and event_types(d) == ["online"]


def test_alarm_reports_become_faults_with_one_event_per_change() -> None:
    d = can_driver(heartbeat_ms=500)
    encoder = can_events("00ff00eb08080808")[0]  # manual: encoder fault
    d.unsolicited(encoder, 0.0)
    d.unsolicited(encoder, 0.5)
    d.unsolicited(can_events("00ff00eb0a0a0a0a")[0], 1.0)
    d.unsolicited(can_events("00fe0021001e043f")[0], 1.5)  # heartbeats again: alarm gone
    events = [e for e in d.drain_events() if e.type == "fault"]
    assert [e.fields for e in events] == [
        {"faults": ["encoder_fault"], "raised": ["encoder_fault"], "cleared": []},
        {"faults": ["over_current", "encoder_fault"], "raised": ["over_current"], "cleared": []},
        {"faults": [], "raised": [], "cleared": ["over_current", "encoder_fault"]},
    ]
    d.unsolicited(can_events("00ff00eb81818181")[0], 2.0)  # running + external: no fault
    assert event_types(d) == [] and d.telemetry(2.0)["faults"] == []


def test_no_such_register_changes_nothing_and_is_reported() -> None:
    d = can_driver()
    request = plan(d, '{"op":"set_mode","mode":"velocity"}')[0]
    with pytest.raises(DeviceRefusedError, match="no register 0x19"):
        d.apply(request, can_events("00ff00190000002f"), 0.0)
    assert d.machine.settings.mode is None and d.machine.expected().mode is None
    assert event_types(d) == ["rejected"]


# --- RS232 ---------------------------------------------------------------------------------------


def test_rs232_position_sequence_gives_the_manuals_frames() -> None:
    """Manual 8.2.2 part one, and the acknowledged halves make the target."""
    d = rs_driver()
    steps = [
        ('{"op":"set_mode","mode":"position"}', ["0200d0d2"]),
        ('{"op":"set_max_speed","rpm":60}', ["1d00a4c1"]),
        ('{"op":"enable"}', ["00000101"]),
        ('{"op":"move","position":10000}', ["50000050", "0527103c"]),
        ('{"op":"move","position":-10000}', ["50ffff4e", "05d8f0cd"]),
    ]
    for text, frames in steps:
        requests = plan(d, text)
        assert wire(requests) == frames, text
        run(d, requests)
    # The sequence leaves the position mode as the drive had it, not known here: a target
    # may be a step from where the shaft was, so where it ends is not known either.
    assert d.telemetry(0)["target"] is None


def test_rs232_move_before_enable_is_refused() -> None:
    d = rs_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"position"}'))
    with pytest.raises(CommandError, match="before enable"):
        plan(d, '{"op":"move","position":10000}')


def test_rs232_init_leaves_no_speed_or_torque_preset_as_can_does() -> None:
    """A speed preset before the gateway came starts the motor at the next enable (8.1.2
    (4)): the monitor, then 0 rpm and 0 A (the mode unknown), no release; 0 rpm alone once the
    mode is known as velocity; nothing once a client enabled the motor (outside wire audit:
    RS232 sent only the monitor)."""
    d = rs_driver()
    assert wire(d.init()) == ["800080", "06000006", "08000008"]
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'))
    assert wire(d.init()) == ["800080", "06000006"]
    run(d, plan(d, '{"op":"enable"}'))
    assert wire(d.init()) == ["800080"]


def test_a_reset_writes_0_rpm_before_it_enables() -> None:
    """A speed preset at the enable would start the motor (outside wire audit: the enable
    went first, leaning on the e-stop's 0 rpm having been taken)."""
    d = can_driver()
    run(d, plan(d, '{"op":"set_mode","mode":"velocity"}'))
    run(d, plan(d, '{"op":"enable"}'))
    d.safe_stop()
    assert wire(d.hold_still()) == ["001#00fa001100000000", "001#00fa00100000001f"]


def test_rs232_poll_is_the_monitor_and_its_reply_becomes_telemetry() -> None:
    d = rs_driver()
    (request,) = d.poll()
    assert wire([request]) == ["800080"] and request.expected.frames == 8 and request.idempotent
    assert d.init()[0] == request
    d.apply(request, rs_events(MANUAL_MONITOR), 0.0)
    state = d.telemetry(0)
    assert (state["voltage_v"], state["current_ma"], state["position"]) == (28, 170, 10000)
    assert state["speed_rpm"] == pytest.approx(98.9, abs=0.1)
    assert state["enabled"] is True  # status word 01: started
    assert state["faults"] == [] and event_types(d) == []


def test_rs232_status_word_faults_emit_once_and_a_stop_shows_disabled() -> None:
    d = rs_driver()
    over_current = MANUAL_MONITOR.replace("80000181", "80000282")
    for _ in range(2):
        d.apply(d.poll()[0], rs_events(over_current), 0.0)
    d.apply(d.poll()[0], rs_events(MANUAL_MONITOR.replace("80000181", "80000080")), 1.0)
    assert [e.fields["faults"] for e in d.drain_events()] == [["over_current"], []]
    assert d.telemetry(1)["enabled"] is False


def test_rs232_keepalive_is_the_monitor_and_stop_is_speed_zero_then_disable() -> None:
    d = velocity_driver(rs_driver(), rpm=50)
    assert wire(plan(d, '{"op":"velocity","rpm":-50}')) == ["06ff787d"]
    assert d.keepalive(0.0) is None
    run(d, plan(d, '{"op":"enable"}'))
    period, request = d.keepalive(0.0)
    assert period == 0.8 and wire([request]) == ["800080"]
    assert wire(d.safe_stop()) == ["06000006", "00000000"]
    request = Zlac706Rs232Driver.follow_request([(d, d.follow_target({"rpm": 50}))])
    assert wire([request]) == ["0600888e"]  # manual: 50 rpm


def test_rs232_refuses_current_gains_and_speed_outside_velocity_mode() -> None:
    d = rs_driver()
    with pytest.raises(CommandError, match="current_kp"):
        plan(d, '{"op":"set_gain","gain":"current_kp","value":5}')
    run(d, plan(d, '{"op":"set_mode","mode":"torque"}'))
    with pytest.raises(CommandError, match="velocity mode"):
        plan(d, '{"op":"velocity","rpm":50}')
    assert wire(plan(d, '{"op":"torque","current_a":8}')) == ["0809c4d5"]


# --- end to end: the real bus owners against the simulator ------------------------------------


def test_rs232_through_the_bus_owner_and_the_simulator() -> None:
    baud = 115_200
    timing = link_timing("zlac706_rs232", baud, margin_s=0.05)
    with SerialSimulator(rs_codec, [sim.Zlac706Rs232Device(1)], baudrate=baud) as simulator:
        owner = SerialBusOwner(simulator.port, rs_codec, timing, BusCounters(time.perf_counter()))
        owner.open()
        try:
            d = rs_driver()

            def go(requests: list[Request]) -> None:
                for r in requests:
                    exchange = owner.exchange(r)
                    d.heard(exchange.end)
                    d.apply(r, exchange.reply, exchange.end)

            go(d.init())
            assert d.online and d.telemetry(0)["voltage_v"] is not None
            go(plan(d, '{"op":"set_mode","mode":"velocity"}'))
            go(plan(d, '{"op":"velocity","rpm":100}'))
            go(plan(d, '{"op":"enable"}'))
            go(d.poll())
            assert d.telemetry(0)["enabled"] is True and d.keepalive(0.0) is not None
            go(d.safe_stop())
            go(d.poll())
            assert d.telemetry(0)["enabled"] is False and d.keepalive(0.0) is None
        finally:
            owner.close()


def test_can_through_the_bus_owner_and_the_simulator() -> None:
    channel = f"zlac706-driver-test-{time.perf_counter_ns()}"
    device_bus = can.Bus(interface="virtual", channel=channel)
    node = sim.Zlac706CanDevice(1, heartbeat_ms=50)
    d = can_driver(heartbeat_ms=50)
    timing = link_timing("zlac706_can", 500_000, margin_s=0.05)
    with CanSimulator(can_codec, [node], bus=device_bus):
        owner = CanBusOwner("virtual", channel, {}, can_codec, timing,
                            BusCounters(time.perf_counter()), on_unsolicited=d.unsolicited)
        owner.open()

        def go(requests: list[Request]) -> None:
            for r in requests:
                exchange = owner.exchange(r)
                d.heard(exchange.end)
                d.apply(r, exchange.reply, exchange.end)

        try:
            go(d.init())
            for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"velocity","rpm":100}',
                         '{"op":"enable"}'):
                go(plan(d, text))
            owner.idle_until(time.perf_counter() + 0.3)  # heartbeats: online, measured
            assert d.online and d.telemetry(0)["measured"] is True
            go([d.keepalive(time.perf_counter())[1]])
            assert d.telemetry(0)["speed_rpm"] > 0
            node.inject_fault("encoder", time.perf_counter())
            owner.idle_until(time.perf_counter() + 0.3)
            assert d.telemetry(0)["faults"] == ["encoder_fault"]
            assert event_types(d) == ["online", "fault"]
            go(d.safe_stop())
            assert d.keepalive(0.0) is None
        finally:
            owner.close()
        d.check_heartbeat(time.perf_counter() + 1.0)
        assert not d.online and event_types(d) == ["offline"]


def test_enabled_in_position_mode_the_drive_holds_at_its_new_zero() -> None:
    """The manual (5.1): enabled in position mode, the drive takes where the shaft is as its
    zero. A target from before (30000) is not where it stands: a stream starting from it
    would jump. Nor is a counter back at 0 then a reboot."""
    d = position_driver(can_driver(heartbeat_ms=10), '{"op":"set_position_mode","relative":false}',
                        '{"op":"enable"}', '{"op":"move","position":100000}')
    d.unsolicited(can_events("00fe0020000186a0")[0], 1.0)  # at 100000
    run(d, plan(d, '{"op":"disable"}'))
    run(d, plan(d, '{"op":"set_position_ramp","accel_ms":100,"decel_ms":100}'))  # no enable
    telemetry = d.telemetry(1.0)
    assert (telemetry["target"], telemetry["position"]) == (100000, 100000)
    run(d, plan(d, '{"op":"enable"}'))
    telemetry = d.telemetry(1.1)
    assert (telemetry["target"], telemetry["position"]) == (0, 0)
    d.unsolicited(can_events("00fe002000000000")[0], 1.2)  # the new zero
    assert "rebooted" not in event_types(d)
    unknown = position_driver(can_driver())
    unknown.machine.settings = Settings(mode=Mode.POSITION, target_position=500)  # enabled?
    run(unknown, plan(unknown, '{"op":"enable"}'))
    assert unknown.telemetry(0.0)["target"] is None  # it may have been enabled already


def test_writes_taken_out_unsent_are_not_counted_on() -> None:
    """A command taken out before it went (expired, withdrawn, its bus lost) set nothing:
    judged as if it had landed, a position stream could go to a drive still relative."""
    d = position_driver(can_driver(), '{"op":"set_position_mode","relative":true}',
                        '{"op":"enable"}')
    plan(d, '{"op":"set_position_mode","relative":false}')
    assert d.follows == "position"
    tell_unsent(Job("wheel", deque()), {"wheel": d})
    assert d.follows is None and d.machine.expected().relative is True


def test_a_stale_stream_writes_no_speed_after_a_mode_change_queued() -> None:
    d = velocity_driver(can_driver(), rpm=0)
    plan(d, '{"op":"set_mode","mode":"position"}')
    assert d.stale_stream() == []


def test_after_a_disable_whose_answer_was_lost_an_enable_leaves_the_zero_unknown() -> None:
    """The disable may have landed (then the enable moved position mode's zero) or not:
    neither target nor position is known until the drive reports, and no position stream
    starts from the old 30000 (it would jump three turns)."""
    d = position_driver(can_driver(heartbeat_ms=10), '{"op":"set_position_mode","relative":false}',
                        '{"op":"enable"}', '{"op":"move","position":30000}')
    d.unsolicited(can_events("00fe002000007530")[0], 1.0)  # at 30000
    (disable,) = plan(d, '{"op":"disable"}')
    d.missed(1.1, disable.frame)
    assert d.machine.settings.enabled is None
    run(d, plan(d, '{"op":"enable"}'))
    telemetry = d.telemetry(1.2)
    assert (telemetry["target"], telemetry["position"]) == (None, None)
    with pytest.raises(CommandError, match="not known now"):
        d.follow_target({"position": 30100})
    d.unsolicited(can_events("00fe002000000000")[0], 1.3)  # it did re-zero
    assert d.follow_target({"position": 100}) == 100 and "rebooted" not in event_types(d)


def test_a_speed_command_taken_out_unsent_is_not_kept_alive() -> None:
    """The keep-alive repeats the speed last written: one still waiting to go is not sent
    ahead of its command, and one that never went (``busy``, nothing sent) must not turn the
    wheel by the keep-alive's hand."""
    d = velocity_driver(can_driver(), rpm=0)
    run(d, plan(d, '{"op":"enable"}'))
    plan(d, '{"op":"velocity","rpm":500}')
    assert d.keepalive(0.0) is None
    d.unsent()
    assert d.keepalive(0.0) is None and d.commanded_speed_raw == 0
