"""A ZLAC706 CAN bus run by the real bus runner: on python-can's virtual bus, and through the
simulated SLCAN adapter on a pty that can be unplugged and plugged back in."""

from __future__ import annotations

import itertools
import time
from concurrent.futures import Future

import can
import pytest

from busgate.codecs import zlac706_can as zcan
from busgate.errors import DeviceRefusedError
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.zlac706_state import Mode, Settings
from busgate.gateway.scheduler.planner import CLIENT_SHARE, Job, Slot
from busgate.gateway.scheduler.tickers import KeepaliveTicker
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim import zlac706 as zlac706_sim
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.slcan import SlcanAdapter
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus

_channels = itertools.count()


def can_bus(interface: str, channel: str, **options) -> CanBus:
    devices = [{"name": "wheel", "kind": "zlac706", "id": 1, "heartbeat_ms": 50, "poll_hz": 5}]
    # The reply margin has room for the simulator, which shares this process and a loaded
    # machine's cores: a late reply is not what these tests are about.
    return CanBus(name="can0", transport="can", interface=interface, channel=channel,
                  reply_margin_ms=50, devices=devices, options=options)


@pytest.fixture
def virtual_channel():
    channel = f"test-can-runner-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    yield channel, simulator
    simulator.stop()


def drive_at(runner, rpm: int, wait_for):
    """Once the wheel is online: velocity mode, enabled, turning at ``rpm``; its driver."""
    wait_for(lambda: runner.drivers["wheel"].online)
    driver = runner.drivers["wheel"]
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}',
                 f'{{"op":"velocity","rpm":{rpm}}}'):
        runner.submit("wheel", driver.parse(text)).result(10)
    return driver


def speed_writes(simulator, since: int = 0) -> list:
    """The speed writes the node received after record ``since``."""
    return [r for r in simulator.recorder.records[since:]
            if r.direction == "rx" and r.wire.startswith("001#00fa0011")]


def test_heartbeats_bring_the_node_online_and_speed_is_kept_alive(
    wait_for, virtual_channel
) -> None:
    """The speed is written again every ``keepalive_period_s`` (0.4 s), inside the node's
    500 ms lock: three keep-alives span more than a lock time, and the shaft never locked
    (the simulated motor says so itself; a slow machine may delay the writes, which a real
    node would not forgive either, but the test measures no gap)."""
    channel, simulator = virtual_channel
    motor = simulator.devices[0].motor
    locks = []
    settle = motor.settle

    def settle_and_note_a_lock(now: float) -> None:
        settle(now)
        if motor.locked:
            locks.append(now)

    motor.settle = settle_and_note_a_lock
    runner = build_bus(can_bus("virtual", channel)).start()
    try:
        driver = drive_at(runner, 300, wait_for)
        assert driver.keepalive_period_s < 0.5, "refreshed before the 500 ms lock"
        wait_for(lambda: (runner.states["wheel"].get("speed_rpm") or 0) > 100)
        mark = len(simulator.recorder.records)
        wait_for(lambda: len(speed_writes(simulator, mark)) >= 3, timeout=10)
        assert locks == [], "the shaft locked"
        assert (runner.states["wheel"].get("speed_rpm") or 0) > 100, "the shaft never locked"
    finally:
        runner.stop()
    stops = [r.wire for r in simulator.recorder.received()]
    assert "001#00fa00100000000f" in stops, "stopping the bus releases the motor"


def test_a_speed_stream_is_the_keep_alive_no_extra_writes_between_ticks(
    wait_for, virtual_channel
) -> None:
    """Each follow tick writes the speed, which is what the keep-alive repeats: while the
    stream runs, the keep-alive waits, so every speed write is a tick. Counted, not timed:
    the keep-alive ticker never comes due (the planner never builds its frame) through more
    than three keep-alive periods' worth of ticks, and the node received every tick."""
    channel, simulator = virtual_channel
    runner = build_bus(can_bus("virtual", channel)).start()
    try:
        driver = drive_at(runner, 100, wait_for)
        (keepalive,) = [t for t in runner.planner.tickers if isinstance(t, KeepaliveTicker)]
        built = []  # each keep-alive frame the planner built, with the tick count then
        build = keepalive.build

        def noted_build(now: float):
            built.append(runner.statistics().follow_intervals)
            return build(now)

        keepalive.build = noted_build
        target = driver.follow_target({"rpm": 200})
        follow_ticks = 3 * driver.keepalive_period_s / driver.follow_period_s

        def streamed(intervals: float) -> bool:  # a client sending its target meanwhile
            runner.follow("wheel", target, "velocity")
            return runner.statistics().follow_intervals > intervals

        wait_for(lambda: streamed(1), timeout=10)
        first, mark = runner.statistics().follow_intervals, len(simulator.recorder.records)
        wait_for(lambda: streamed(first + follow_ticks), timeout=30)
        last = runner.statistics().follow_intervals
        wait_for(lambda: len(speed_writes(simulator, mark)) >= last - first - 1)
    finally:
        runner.stop()
    assert [n for n in built if first <= n < last] == [], "a keep-alive between ticks"


def test_lost_heartbeats_mark_the_node_offline(wait_for, virtual_channel) -> None:
    channel, simulator = virtual_channel
    events = []
    runner = build_bus(can_bus("virtual", channel), on_event=events.append).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        simulator.faults.configure(silent_ids=frozenset({1}))
        simulator.devices[0].heartbeat_s = 0
        wait_for(lambda: not runner.drivers["wheel"].online)
        assert [e.type for e in events].count("offline") == 1
    finally:
        runner.stop()


def test_a_bus_s_can_filters_reach_python_can_which_applies_them() -> None:
    """As plain dicts: a filter of another type (a string was taken) raised in python-can's
    match at every frame, and the bus thread opened the bus again each second."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}",
                               can_filters=[{"can_id": 2, "can_mask": 0x7FF}]))
    runner.owner.open()
    try:
        python_can = runner.owner._bus
        assert python_can is not None and python_can.filters == [{"can_id": 2, "can_mask": 0x7FF}]
        assert [python_can._matches_filters(can.Message(arbitration_id=node, is_extended_id=False))
                for node in (1, 2)] == [False, True]
    finally:
        runner.owner.close()


def test_an_idle_slcan_adapter_s_heartbeats_are_taken_by_a_look(wait_for) -> None:
    """While idle the owner looks at an SLCAN adapter without waiting for a frame (a deadline
    long past), and a look takes the heartbeats that came."""
    channel = f"test-can-slcan-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    adapter = SlcanAdapter(channel).start()
    heard = []
    owner = CanBusOwner("slcan", adapter.port, {"sleep_after_open": 0}, zcan,
                        link_timing("zlac706_can", 500_000, margin_s=0.002), BusCounters(0.0),
                        on_unsolicited=lambda event, when: heard.append(event))
    owner.open()
    try:
        simulator.devices[0].heartbeat_s = 0.01

        def heard_a_heartbeat() -> bool:
            owner.idle_until(0.0)  # a deadline long past: take what is there, wait for nothing
            return any(isinstance(event, zcan.HeartbeatPosition) for event in heard)

        wait_for(heard_a_heartbeat)
    finally:
        owner.close()
        adapter.stop()
        simulator.stop()


def test_slcan_adapter_unplugged_and_back(wait_for, tmp_path) -> None:
    channel = f"test-can-slcan-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    by_id = str(tmp_path / "usb-canable")  # the stable name udev gives a real adapter
    adapter = SlcanAdapter(channel, link=PtyLink(by_id)).start()
    runner = build_bus(can_bus("slcan", by_id, sleep_after_open=0)).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        adapter.unplug()
        wait_for(lambda: not runner.drivers["wheel"].online)
        adapter.replug()
        wait_for(lambda: runner.drivers["wheel"].online, timeout=8)
        assert runner.statistics().reconnects >= 1
    finally:
        runner.stop()
        adapter.stop()
        simulator.stop()


def test_a_write_the_node_refuses_is_answered_device_refused(
    wait_for, virtual_channel, monkeypatch
) -> None:
    """A node without the register written answers ``FF`` (8.1.1): the command fails with
    ``device_refused`` naming the register, where it was answered ok."""
    channel, _ = virtual_channel
    monkeypatch.delitem(zlac706_sim._CAN_WRITES, zcan.CanRegister(0x14))  # a node without it
    runner = build_bus(can_bus("virtual", channel)).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        driver = runner.drivers["wheel"]
        reply = runner.submit("wheel", driver.parse('{"op":"write","register":20,"value":7}'))
        with pytest.raises(DeviceRefusedError, match="node 1 has no register 0x14"):
            reply.result(10)
        ok = runner.submit("wheel", driver.parse('{"op":"write","register":19,"value":100}'))
        assert "state" in ok.result(10)  # the next write, which it has, goes as before
    finally:
        runner.stop()


def test_a_target_judged_before_a_mode_change_never_starts_a_stream_of_the_other_kind() -> None:
    """A speed judged while the wheel was in velocity mode reaches the bus thread after it
    was switched to position mode: it is dropped, told as a refusal, never sent as a
    position (nor fed to a running stream of positions)."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}"))  # not started
    runner.owner.open()
    wheel = runner.drivers["wheel"]
    try:
        wheel.machine.settings = Settings(mode=Mode.POSITION, relative=False, enabled=True)
        runner.follow("wheel", -900.0, "velocity")
        runner._drain_inbox()
        assert not runner.streams.following("wheel")
        [refused] = [e for e in wheel.drain_events() if e.type == "command_refused"]
        assert refused.fields == {"code": "bad_command", "message": (
            "wheel follows positions now (its mode changed since this velocity target was "
            "judged); nothing was sent")}
        runner.follow("wheel", 300.0, "position")
        runner._drain_inbox()
        assert runner.streams.following("wheel")
        runner.follow("wheel", -900.0, "velocity")  # not fed to the stream of positions
        assert runner.streams._streams["wheel"].latest[0] == 300.0
    finally:
        runner.owner.close()


def test_a_command_that_expired_unsent_leaves_the_drive_judged_as_it_was() -> None:
    """``set_position_mode`` absolute found no room on the bus and was answered ``busy``,
    nothing sent: the wheel is still relative, so no position stream may start."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}"))  # not started
    runner.owner.open()
    wheel = runner.drivers["wheel"]
    try:
        wheel.machine.settings = Settings(mode=Mode.POSITION, relative=True, enabled=True)
        future: Future = Future()
        absolute = wheel.parse('{"op":"set_position_mode","relative":false}')
        runner._work.plan_command("wheel", absolute, None, now() + 0.001, future)
        assert wheel.follows == "position"  # as it will be, once the write lands
        time.sleep(0.002)
        runner.planner.decide(now())
        runner._answer_expired()
        assert future.exception(0).code == "busy" and wheel.follows is None
    finally:
        runner.owner.close()


def test_a_speed_command_waiting_to_go_is_not_sent_ahead_of_it_by_the_keep_alive() -> None:
    """The keep-alive repeats the speed that last went: a new speed still waiting in the
    queue is not written by the keep-alive first (twice on the wire, and by the keep-alive's
    hand should its command then be taken out unsent), the command's own write goes."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}"))  # not started
    runner.owner.open()
    wheel = runner.drivers["wheel"]
    try:
        wheel.machine.settings = Settings(mode=Mode.VELOCITY, enabled=True, speed_raw=0)
        future: Future = Future()
        runner._work.plan_command("wheel", wheel.parse('{"op":"velocity","rpm":500}'), None,
                                  now() + 10, future)
        slot = runner.planner.decide(now())
        assert isinstance(slot, Slot) and isinstance(slot.source, Job), slot
        assert slot.request.frame.register == zcan.CanRegister.TARGET_SPEED
    finally:
        runner.owner.close()


def test_a_command_refused_busy_once_planned_leaves_the_drive_judged_as_it_was() -> None:
    """A ``disable`` refused ``busy`` (its client's share of the queue taken) set nothing: the
    motor is still on, so a mode change is still refused (the manual: disable first)."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}"))  # not started
    runner.owner.open()
    wheel = runner.drivers["wheel"]
    try:
        wheel.machine.settings = Settings(mode=Mode.VELOCITY, enabled=True, speed_raw=0)
        stop = wheel.parse('{"op":"velocity","rpm":0}')
        for _ in range(CLIENT_SHARE):
            runner._work.plan_command("wheel", stop, "flood", now() + 10, Future())
        refused: Future = Future()
        runner._work.plan_command("wheel", wheel.parse('{"op":"disable"}'), "flood",
                                  now() + 10, refused)
        assert refused.exception(0).code == "busy"
        assert wheel.machine.expected().enabled is True
        mode: Future = Future()
        runner._work.plan_command("wheel", wheel.parse('{"op":"set_mode","mode":"position"}'),
                                  "other", now() + 10, mode)
        assert "disable first" in str(mode.exception(0))
    finally:
        runner.owner.close()


def test_a_re_enable_or_a_reset_that_never_went_leaves_the_device_e_stopped() -> None:
    """The re-enable op clears the e-stop's latch when it is planned: refused ``busy`` (its
    client's share of the queue taken), nothing sent, the wheel is still e-stopped, and
    motion is refused as before. So with a reset that expired: latched again, and still due
    to be driven again by the next reset."""
    runner = build_bus(can_bus("virtual", f"test-can-runner-{next(_channels)}"))  # not started
    runner.owner.open()
    wheel = runner.drivers["wheel"]
    try:
        wheel.machine.settings = Settings(mode=Mode.VELOCITY, enabled=False, speed_raw=0)
        wheel.estop_latched = True
        stop = wheel.parse('{"op":"velocity","rpm":0}')  # a stop: taken while e-stopped
        for _ in range(CLIENT_SHARE):
            runner._work.plan_command("wheel", stop, "flood", now() + 10, Future())
        refused: Future = Future()
        runner._work.plan_command("wheel", wheel.parse('{"op":"enable"}'), "flood",
                                  now() + 10, refused)
        assert refused.exception(0).code == "busy" and wheel.estopped
        runner.planner.drop_commands()
        wheel.driving_before_estop = True
        reset: Future = Future()
        runner._work.plan_reset("wheel", now() + 0.001, reset, frozenset())
        assert not wheel.estopped and not wheel.driving_before_estop  # as planned
        time.sleep(0.002)
        runner.planner.decide(now())
        runner._answer_expired()
        assert reset.exception(0).code == "busy"
        assert wheel.estopped and wheel.driving_before_estop
    finally:
        runner.owner.close()
