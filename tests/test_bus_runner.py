"""The bus owner and the bus runner against the Inspire LA simulator on a real pty.

These are behaviour tests: commands come back with results, the link comes back after an
unplug, late replies are never taken for the next request's answer, follow streams start and
go stale, the queue says "busy" instead of growing. Timing is asserted only as lower bounds
(the gap), never as upper bounds or rates: this machine is shared and noisy. What needs real
time is waited for, with a generous deadline, and then its outcome is asserted.
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future

import pytest

from busgate.codecs import inspire_la as la
from busgate.errors import BusIOError, BusUnavailableError, BusyError, DeviceTimeoutError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.owner import TX
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.scheduler import link
from busgate.gateway.scheduler import runner as runner_module
from busgate.gateway.scheduler.link import BACKOFF_FIRST_S, BACKOFF_MAX_S
from busgate.gateway.scheduler.planner import CLIENT_SHARE, Job, Priority
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import SerialBus

BAUD = 921_600


@pytest.fixture
def simulator(tmp_path):
    link = PtyLink(str(tmp_path / "usb-la"))
    devices = [InspireLaDevice(1), InspireLaDevice(2)]
    with SerialSimulator(la, devices, baudrate=BAUD, link=link) as sim:
        yield sim


def status(device_id: int) -> Request:
    return Request.of(la, la.ControlCommand(device_id, la.ControlCode.STATUS), idempotent=True)


def owner_for(port: str, margin_s: float = 0.05) -> SerialBusOwner:
    """An owner whose reply window has room for a loaded machine (50 ms margin) unless a test
    needs a tight one."""
    timing = link_timing("inspire_la", BAUD, margin_s=margin_s, gap_s=0.001)
    owner = SerialBusOwner(port, la, timing, BusCounters(now()))
    owner.open()
    return owner


def bus(port: str, reply_margin_ms: float = 20.0, **device) -> SerialBus:
    """la1 and la2 polled at 50 Hz. The reply margin has room for the simulator, which shares
    this process and a loaded machine's cores, unless a test needs the default's."""
    devices = [
        {"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 50, **device},
        {"name": "la2", "kind": "inspire_la", "id": 2, "poll_hz": 50},
    ]
    return SerialBus(
        name="uart0",
        transport="serial",
        port=port,
        baudrate=BAUD,
        reply_margin_ms=reply_margin_ms,
        devices=devices,
    )


def test_owner_exchange_and_timeout_is_not_a_lost_link(simulator) -> None:
    owner = owner_for(simulator.port)
    try:
        exchange = owner.exchange(status(1))
        assert isinstance(exchange.reply[0], la.StatusReply) and exchange.reply[0].device_id == 1
        # From before the write (start - write_s: the write call may return late on a loaded
        # host) to the reply's last byte: at least both frames' time on the emulated wire.
        assert exchange.end - (exchange.start - exchange.write_s) >= (8 + 22) * 10 / BAUD
        with pytest.raises(DeviceTimeoutError):
            owner.exchange(status(9))
        assert owner.is_open, "a silent device does not close the port"
        assert owner.counters.timeouts == 1
    finally:
        owner.close()


def test_a_late_reply_is_flushed_not_taken_for_the_next_answer(wait_for, simulator) -> None:
    owner = owner_for(simulator.port)  # the reply comes 300 ms late: far past its 50 ms margin
    try:
        simulator.faults.configure(late_rate=1.0, late_s=0.3)
        with pytest.raises(DeviceTimeoutError):
            owner.exchange(status(1))
        simulator.faults.configure(late_rate=0.0)
        # The late reply is in the port once the simulator has it on record (it records a
        # reply after writing it); the next exchange must flush it, not take it.
        wait_for(lambda: any(r.direction == "tx" for r in simulator.recorder.records))
        reply = owner.exchange(status(2)).reply
        assert [r.device_id for r in reply] == [2]
        assert owner.counters.late_replies >= 1
    finally:
        owner.close()


def test_an_unplugged_adapter_raises_bus_io_error(wait_for, simulator) -> None:
    owner = owner_for(simulator.port)
    simulator.unplug()
    wait_for(lambda: not simulator.link.plugged)
    with pytest.raises(BusIOError):
        owner.exchange(status(1))
    assert not owner.is_open


def test_a_group_move_sent_through_one_actuator_switches_on_the_other_it_moves(
    wait_for, simulator
) -> None:
    """Manual 3.5.4: a paused actuator is switched on by a new target, a group's too. Sent
    through la2's command, the F2 frame moved la1, whose state still said paused."""
    runner = build_bus(bus(simulator.port)).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        la1, la2 = runner.drivers["la1"], runner.drivers["la2"]
        runner.submit("la1", la1.parse('{"op":"pause"}')).result(10)
        assert la1.power.value == "paused"
        group = '{"op":"group_move","targets":[{"id":1,"position":700},{"id":2,"position":800}]}'
        runner.submit("la2", la2.parse(group)).result(10)
        assert la1.power.value == "on" and la2.power.value == "on"
        wait_for(lambda: runner.states["la1"]["target"] == 700)  # it did move la1, as read
    finally:
        runner.stop()


def test_runner_carries_out_commands_and_polls(wait_for, simulator) -> None:
    runner = build_bus(bus(simulator.port)).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        driver = runner.drivers["la1"]
        result = runner.submit("la1", driver.parse('{"op":"move","position":1500}')).result(10)
        assert result["state"]["target"] == 1500
        read = runner.submit("la1", driver.parse('{"op":"read","index":2,"length":1}')).result(10)
        assert read["data"] == "01"
        wait_for(lambda: runner.states["la1"]["position"] > 100)
        stats = runner.statistics()
        assert stats.frames_in > 0 and stats.smallest_gap_s >= 0.001
    finally:
        runner.stop()


@pytest.mark.parametrize("cut_short", [False, True])
def test_a_poll_decided_before_its_moment_starts_as_decided_unless_its_wait_was_cut_short(
    monkeypatch, simulator, cut_short
) -> None:
    """This thread plays the bus thread, on a clock that stands still. A poll due within
    ``PREPARE_S`` is decided then; when its wait reaches the moment it goes as decided (no
    second decision after the gap); when new work (an e-stop) cut the wait short, nothing is
    sent: the next turn decides again, the new work first."""
    runner = build_bus(bus(simulator.port))  # not started
    moment = now()
    monkeypatch.setattr(runner_module, "now", lambda: moment)
    for poller in runner.pollers:
        poller.next_due = moment + runner_module.PREPARE_S / 2
    waits: list[float] = []
    sent: list[tuple] = []

    def wait_until(deadline: float, *, precise: bool = True) -> bool:
        waits.append(deadline)
        return not cut_short

    monkeypatch.setattr(runner, "_wait_until", wait_until)
    monkeypatch.setattr(runner, "_execute", lambda slot, at=None: sent.append((slot, at)))
    runner._step()
    assert waits == [moment + runner_module.PREPARE_S / 2]  # one wait, to the poll's moment
    if cut_short:
        assert sent == []
    else:
        [(slot, at)] = sent
        assert slot.priority is Priority.POLL and at is None  # at its moment already


LEAD_S = 50e-6


@pytest.mark.parametrize(
    ("line", "woken", "goes_on", "learns"),
    [("uart", "reached", True, True),
     ("uart", "cut_short_before_its_last_stretch", False, False),
     ("uart", "cut_short_in_its_last_stretch", True, True),
     ("uart", "an_estop_in_its_last_stretch", False, False),
     ("uart", "an_estop_as_it_ends", False, True),
     ("can", "reached", True, True),
     ("can", "cut_short_before_its_last_stretch", False, False),
     ("can", "an_estop_as_it_ends", False, False)],
)  # fmt: skip
def test_a_precise_wait_ends_at_its_lead_and_only_early_work_or_an_estop_cuts_it_short(
    monkeypatch, simulator, line, woken, goes_on, learns
) -> None:
    """This thread plays the bus thread, on a fake clock, with a learnt lead of 50 us. On a
    UART line the owner idles until the lead before the deadline (one wait: the rest is the
    caller's spin); on a line with frames to take in (CAN), until ``UNINTERRUPTED_S`` before
    it, and a wait only an e-stop cuts short (a real one, some 0.95 ms) goes on to the lead.
    Either learns how late it woke from the wait that slept to the lead. New work cuts the wait
    short before its last ``UNINTERRUPTED_S``, not in it (the wait goes on to the lead); an
    e-stop cuts it short there too, and stops it from going on even once it has ended."""
    runner = build_bus(bus(simulator.port))  # not started
    runner.devices.take_news()  # nothing to publish: a pause sleeps
    if line == "can":
        monkeypatch.setattr(runner.owner, "idle_batch_s", 0.008)
    idles_to = {"uart": LEAD_S, "can": runner_module.UNINTERRUPTED_S}[line]
    clock = [100.0]
    deadline = 100.005
    monkeypatch.setattr(runner_module, "now", lambda: clock[0])
    monkeypatch.setattr(runner_module, "wake_lead", lambda: LEAD_S)
    learnt: list[float] = []
    monkeypatch.setattr(runner_module, "woke_for", learnt.append)
    asked: list[float] = []
    reached = woken in ("reached", "an_estop_as_it_ends")

    def idle_until(until: float, pause: Callable[[float], bool]) -> bool:
        asked.append(until)
        if clock[0] < until:
            pause(0.0)
        clock[0] = until + 20e-6 if reached else {
            "cut_short_before_its_last_stretch": deadline - 0.0015,
            "cut_short_in_its_last_stretch": deadline - 0.0005,
            "an_estop_in_its_last_stretch": deadline - 0.0005}[woken]  # fmt: skip
        if woken.startswith("an_estop"):
            runner.estop()
        return reached

    monkeypatch.setattr(runner.owner, "idle_until", idle_until)
    assert runner._wait_until(deadline) is goes_on
    assert asked == [pytest.approx(deadline - idles_to)]
    assert learnt == ([pytest.approx(deadline - LEAD_S)] if learns else [])


def test_a_wait_that_did_not_sleep_learns_nothing_and_one_not_precise_has_no_lead(
    monkeypatch, simulator
) -> None:
    runner = build_bus(bus(simulator.port))  # not started
    runner.devices.take_news()
    clock = [100.0]
    monkeypatch.setattr(runner_module, "now", lambda: clock[0])
    monkeypatch.setattr(runner_module, "wake_lead", lambda: LEAD_S)
    learnt: list[float] = []
    monkeypatch.setattr(runner_module, "woke_for", learnt.append)
    asked: list[float] = []
    monkeypatch.setattr(
        runner.owner, "idle_until", lambda until, pause: asked.append(until) or True
    )
    clock[0] = 100.005 - LEAD_S / 2  # past the lead already: nothing to sleep
    assert runner._wait_until(100.005) is True
    assert learnt == []
    assert runner._wait_until(100.008, precise=False) is True
    assert asked[-1] == pytest.approx(100.008)
    runner.estop()
    assert runner._wait_until(100.008, precise=False) is False, "an e-stop is due"


def telling_runner(monkeypatch, port: str, clock: list[float], publish_takes: float):
    """A runner (not started) on a fake clock whose publishing takes ``publish_takes``; the
    devices it told a state of, and the pauses it waited (each wait as ``woken`` says)."""
    runner = build_bus(bus(port))
    runner.devices.take_news()
    monkeypatch.setattr(runner_module, "now", lambda: clock[0])
    told: list[str] = []
    monkeypatch.setattr(runner.telemetry, "on_state", lambda device, state: told.append(device))
    publish = runner.telemetry.publish

    def slow_publish(moment: float) -> list[str]:
        clock[0] += publish_takes
        return publish(moment)

    monkeypatch.setattr(runner.telemetry, "publish", slow_publish)
    return runner, told


@pytest.mark.parametrize(
    ("news", "publish_takes", "woken", "cut_short", "waits"),
    [
        (None, 0.0, False, False, 0.008),  # nothing to tell: the whole pause
        ("state", 0.003, False, False, 0.005),  # told in the pause, which goes on for the rest
        ("state", 0.003, True, True, 0.005),  # new work cut the rest short
        ("state", 0.009, False, False, None),  # telling took the pause: back to look, no wait
        ("state", 0.009, True, True, None),  # ... and new work came meanwhile
        ("event", 0.003, False, True, None),  # what is planned may change: decided again
    ],
)
def test_an_idle_pause_tells_a_devices_news_and_goes_on_unless_it_was_an_event(
    monkeypatch, simulator, news, publish_takes, woken, cut_short, waits
) -> None:
    """A heartbeat bus takes news in every batch: told in the pause, it does not turn the
    loop (and decide) for each batch; an event (a device came or went) does."""
    runner, told = telling_runner(monkeypatch, simulator.port, [100.0], publish_takes)
    waited: list[float] = []
    monkeypatch.setattr(runner._wake, "wait", lambda seconds: waited.append(seconds) or woken)
    if woken:
        runner._wake.set()
    driver = runner.drivers["la1"]
    if news is not None:
        runner.devices.touched(driver)
    if news == "event":
        driver.emit("offline", reason="test")
    assert runner._pause(0.008) is cut_short
    assert told == ([] if news is None else ["la1"]), "the news is told either way"
    assert not runner.devices.has_news
    assert waited == ([] if waits is None else [pytest.approx(waits)])
    if news == "event":  # the next batch, with news and no event, goes on again
        runner.devices.touched(driver)
        assert runner._pause(0.008) is False and len(waited) == 1


@pytest.mark.parametrize("publish_takes", [0.0005, 0.0025])
def test_events_told_while_idling_decide_again_even_once_in_the_last_stretch(
    monkeypatch, simulator, publish_takes
) -> None:
    """A CAN-like line idles to ``UNINTERRUPTED_S`` before a prepared tick; a batch there
    that brought an event (a rebooted device: its tick is stale) makes the runner decide
    again, even when telling it ran past the last stretch's start."""
    clock = [100.0]
    runner, _ = telling_runner(monkeypatch, simulator.port, clock, publish_takes)
    monkeypatch.setattr(runner.owner, "idle_batch_s", 0.008)
    deadline = 100.003
    monkeypatch.setattr(runner_module, "wake_lead", lambda: LEAD_S)
    monkeypatch.setattr(runner_module, "woke_for", lambda asked: None)

    def idle_until(until: float, pause: Callable[[float], bool]) -> bool:
        clock[0] = until - 0.002  # a batch taken in 2 ms before the last stretch
        runner.devices.touched(runner.drivers["la1"])
        runner.drivers["la1"].emit("rebooted", evidence="test", restoring=0)
        return not pause(0.002)

    monkeypatch.setattr(runner.owner, "idle_until", idle_until)
    assert runner._wait_until(deadline) is False
    assert clock[0] >= deadline - runner_module.UNINTERRUPTED_S or publish_takes < 0.002


def test_a_command_to_a_silent_device_fails_without_stopping_its_neighbour(
    wait_for, simulator
) -> None:
    """la1 goes silent: its command fails, it goes offline and is asked again every
    ``OFFLINE_PROBE_S`` (each time a poll tried three times), while la2, polled twelve times as
    often, keeps answering. Counted in exchanges, not per second, so a slow machine (which
    skips polls of both alike) does not change the outcome; la1 asked at its own 50 Hz while
    offline would leave la2 about one poll per probe."""
    events = []
    runner = build_bus(bus(simulator.port), on_event=events.append).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        simulator.faults.configure(silent_ids=frozenset({1}))
        future = runner.submit("la1", runner.drivers["la1"].parse('{"op":"status"}'))
        with pytest.raises(DeviceTimeoutError):
            future.result(10)
        wait_for(lambda: not runner.drivers["la1"].online)
        ok = runner.submit("la2", runner.drivers["la2"].parse('{"op":"status"}')).result(10)
        assert ok["state"]["online"] is True
        mark = len(simulator.recorder.received())

        def asked(device_id: int) -> int:
            return sum(r.device_id == device_id for r in simulator.recorder.received()[mark:])

        wait_for(lambda: asked(1) >= 3 * 6, timeout=30)  # la1 probed six times more
        probes, polls = asked(1) / 3, asked(2)
        assert runner.drivers["la2"].online and not runner.drivers["la1"].online
    finally:
        runner.stop()
    assert [e.device for e in events if e.type == "offline"] == ["la1"], "la2 went offline"
    assert polls >= 4 * probes, f"la2 polled {polls} times beside {probes:.0f} probes of la1"


def test_follow_stream_goes_out_at_its_period_and_goes_stale(wait_for, simulator) -> None:
    events = []
    runner = build_bus(bus(simulator.port, follow_period_ms=10), on_event=events.append).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        target = runner.drivers["la1"].follow_target({"position": 1200})

        def streamed() -> bool:  # a client sending its target until ten intervals went out
            runner.follow("la1", target, "position")
            return runner.statistics().follow_intervals > 10

        wait_for(streamed, timeout=10)
        stale_before = [e.type for e in events].count("stream_stale")
        wait_for(lambda: [e.type for e in events].count("stream_stale") > stale_before)
        stats = runner.statistics()
        assert stats.follow_error_min_s >= 0, "no follow interval is shorter than the period"

        def ticks() -> int:
            return sum(r.frame == "FollowCommand" for r in simulator.recorder.received())

        wait_for(lambda: ticks() > 10)  # what the host sent reached the device
    finally:
        runner.stop()


def test_estop_goes_ahead_and_stops_every_device(wait_for, simulator) -> None:
    runner = build_bus(bus(simulator.port)).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        runner.estop().result(10)
        controls = [r.wire for r in simulator.recorder.received() if r.frame == "ControlCommand"]
        assert la.encode(la.ControlCommand(1, la.ControlCode.ESTOP)).hex() in controls
        assert la.encode(la.ControlCommand(2, la.ControlCode.ESTOP)).hex() in controls
        refused = runner.submit("la1", runner.drivers["la1"].parse('{"op":"move","position":5}'))
        with pytest.raises(Exception, match="enable"):
            refused.result(10)
    finally:
        runner.stop()


def test_letting_estops_go_waits_for_each_bus_within_one_bound_in_all(monkeypatch) -> None:
    """Rule 1: whoever handed e-stops over waits for each bus's first exchange, but never
    longer than ``ESTOP_SENT_S`` in all, however many buses are slow to say so."""
    clock = [100.0]
    monkeypatch.setattr(runner_module, "now", lambda: clock[0])
    given: list[float] = []

    class Slow:
        def estop_sent(self, timeout: float) -> bool:
            given.append(timeout)
            clock[0] += 0.003  # this bus took 3 ms
            return False

    runner_module.let_estops_go([Slow(), Slow(), Slow()])
    bound = runner_module.ESTOP_SENT_S
    assert given == pytest.approx([bound, bound - 0.003, 0.0])


def test_a_target_or_play_judged_before_an_estop_and_landing_after_it_moves_nothing(
    wait_for, simulator
) -> None:
    """A follow target, a ramp or a trajectory judged while the device could move, handed
    over behind an e-stop (or, with bus workers, before the gateway's process heard of it),
    starts nothing: the bus goes on, a stream's refusal is an event, a play's is its refusal."""
    events = []
    runner = build_bus(bus(simulator.port, follow_period_ms=10), on_event=events.append).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        target = runner.drivers["la1"].follow_target({"position": 1200})
        estop = runner.estop()
        runner.follow("la1", target, "position")  # behind the e-stop in the inbox
        runner.ramp("la2", runner.drivers["la2"].follow_target({"position": 900}), "position")
        runner.play({"la2": lambda t_s: {"position": 900}}, now() + 0.05)
        estop.result(10)
        mark = len(simulator.recorder.received())
        wait_for(lambda: runner.plays.refusal("la2") is not None)
        time.sleep(0.1)
        ticks = [
            r
            for r in simulator.recorder.received()[mark:]
            if r.frame in ("FollowCommand", "GroupFollowCommand")
        ]
        assert ticks == []
        refused = [e.fields["code"] for e in events if e.type == "command_refused"]
        assert refused == ["estopped", "estopped"]
        assert runner.statistics().reconnects == 0 and runner.owner.is_open
    finally:
        runner.stop()


def test_an_estop_latches_every_device_before_it_ends_their_plays(wait_for, simulator) -> None:
    """A trajectory's watcher, on another thread, that sees its play ended must see its
    devices e-stopped too (its result says ``estop``, not "stopped with every device")."""
    runner = build_bus(bus(simulator.port)).start()
    seen: list[bool] = []
    end_all = runner.plays.end_all

    def ending(*args, **kwargs):
        seen.append(all(driver.estopped for driver in runner.drivers.values()))
        return end_all(*args, **kwargs)

    runner.plays.end_all = ending
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        runner.estop().result(10)
        assert seen == [True]
    finally:
        runner.stop()


def test_an_estops_first_frame_goes_before_the_streams_it_ends(wait_for, simulator) -> None:
    """What an e-stop ends (streams, plays, waiting commands: events and answers) is ended
    once its first frame is out, not before: that Python would hold the frame back, and with
    several buses on one interpreter, every bus's frame (``work.plan_estop``)."""
    events = []
    runner = build_bus(bus(simulator.port, follow_period_ms=10), on_event=events.append).start()
    order: list[str] = []
    estops = {la.encode(la.ControlCommand(i, la.ControlCode.ESTOP)) for i in (1, 2)}
    runner.owner.tap = lambda frame: order.append("e-stop frame") if frame[2] in estops else None
    end_all = runner.streams.end_all
    runner.streams.end_all = lambda why: (order.append(f"streams ended: {why}"), end_all(why))
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        runner.follow("la1", runner.drivers["la1"].follow_target({"position": 1200}), "position")
        wait_for(lambda: any(r.frame == "FollowCommand" for r in simulator.recorder.received()))
        runner.estop().result(10)
        assert order[:2] == ["e-stop frame", "streams ended: estop"]
        assert [e.fields["reason"] for e in events if e.type == "stream_stopped"] == ["estop"]
    finally:
        runner.stop()


def test_an_estop_answers_the_commands_it_took_out_once_its_frame_is_out(simulator) -> None:
    """The commands waiting when an e-stop comes are taken out at once and answered
    ``estopped`` after its first exchange (``end_estopped``), or when the bus is lost or
    stops before it; a reset handed over behind the e-stop is not one of them."""
    runner = build_bus(bus(simulator.port))  # not started: the test is the bus thread
    runner.owner.open()
    work = runner._work
    try:
        waiting, reset = Future(), Future()
        work.queue_job(Job("la1", deque([status(1)]), future=waiting))
        work.plan_estop(Future())
        work.plan_reset(None, now() + 10, reset, frozenset())
        assert not waiting.done()
        work.end_estopped()
        assert waiting.exception(0).code == "estopped"
        assert not reset.done() and runner.planner.queued == 1
        work.end_estopped()  # once
        assert not reset.done()

        waiting = Future()
        work.queue_job(Job("la2", deque([status(2)]), future=waiting))
        work.plan_estop(Future())
        work.end_everything("shutdown", "shutdown", BusUnavailableError("bus uart0 is stopping"))
        assert waiting.exception(0).code == "estopped"
        assert reset.exception(0).code == "estopped"  # it was waiting when this e-stop came
    finally:
        runner.owner.close()


def test_an_estop_leaves_a_command_that_only_reads_waiting_and_takes_a_move_out(
    simulator,
) -> None:
    """A client's read waiting when an e-stop came was answered ``estopped``, a refusal the
    API documents for motion only (a stuck e-stop button refused 3 of 20 reads): a command
    whose frames only read moves nothing, and waits behind the e-stop instead."""
    runner = build_bus(bus(simulator.port))  # not started: the test is the bus thread
    runner.owner.open()
    work, driver = runner._work, runner.drivers["la1"]
    try:
        read, move = Future(), Future()
        for command, future in (('{"op":"status"}', read), ('{"op":"move","position":700}', move)):
            work.plan_command("la1", driver.parse(command), None, now() + 10, future)
        work.plan_estop(Future())
        work.end_estopped()
        assert move.exception(0).code == "estopped"
        assert not read.done() and runner.planner.queued == 1
        step_while_stopping(runner)
        deadline = now() + 10
        while not read.done() and now() < deadline:
            runner._step()
        assert read.result(0)["state"]["device"] == "la1"
    finally:
        runner.owner.close()


def test_a_client_past_its_share_of_the_queue_is_told_busy_and_another_still_gets_in(
    simulator,
) -> None:
    runner = build_bus(bus(simulator.port))  # not started: nothing leaves the queue
    runner.owner.open()
    work, driver = runner._work, runner.drivers["la1"]
    move = driver.parse('{"op":"move","position":700}')
    try:
        futures = [Future() for _ in range(CLIENT_SHARE + 1)]
        for future in futures:
            work.plan_command("la1", move, "flood", now() + 10, future)
        refused = futures[-1].exception(0)
        assert refused.code == "busy"
        assert f"client 'flood' has {CLIENT_SHARE} commands waiting" in str(refused)
        other = Future()
        work.plan_command("la2", move, "arm-ctl", now() + 10, other)
        assert not other.done() and runner.planner.queued == CLIENT_SHARE + 1
    finally:
        runner.owner.close()


def test_follow_mode_targets_by_command_keep_the_follow_period_and_leave_a_stream_alone(
    simulator,
) -> None:
    """The manual takes follow-mode targets at a fixed period: a command's follow (or a group
    follow naming the device) is refused, nothing queued, while the command carrying the
    last one a command sent it waits to go out, sooner than the device's follow period after
    that one went on the wire, and while a stream follows the device."""
    runner = build_bus(bus(simulator.port, follow_period_ms=10))  # not started: the test runs it
    runner.owner.open()
    work, la1 = runner._work, runner.drivers["la1"]

    def sent(device: str, text: str) -> Future:
        future = Future()
        work.plan_command(device, runner.drivers[device].parse(text), None, now() + 10, future)
        return future

    follow = '{"op":"follow","position":900}'
    group = '{"op":"group_follow","targets":[{"id":1,"position":900},{"id":2,"position":900}]}'
    try:
        waiting = sent("la1", follow)
        refused = sent("la1", follow).exception(0)
        assert refused.code == "busy" and "still waits to go out" in str(refused)
        time.sleep(0.011)  # a period since it was planned: it has not gone yet, though
        assert sent("la2", group).exception(0).code == "busy", "la1 is in it"
        assert runner.planner.queued == 1
        while not waiting.done():  # the bus thread's turns: the follow goes on the wire
            runner._step()
        refused = sent("la1", follow).exception(0)
        assert refused.code == "busy" and "once every 10 ms" in str(refused)
        time.sleep(0.011)
        grouped = sent("la2", group)
        while not grouped.done():
            runner._step()
        time.sleep(0.021)  # la2's follow period: 20 ms
        runner.streams.start(la1, la1.follow_target({"position": 1000}), now())
        refused = sent("la1", follow).exception(0)
        assert refused.code == "busy" and "follow key" in str(refused)
        assert not sent("la2", '{"op":"follow","position":800}').done()
        # a move is no follow, but the stream's next tick would overwrite it (``work``)
        refused = sent("la1", '{"op":"move","position":800}').exception(0)
        assert refused.code == "busy" and "follows a stream" in str(refused)
        assert runner.planner.queued == 1
    finally:
        runner.owner.close()


def test_a_stop_the_queue_refuses_leaves_the_stream_it_would_have_ended(simulator) -> None:
    """A stop ends its device's stream once it is queued: refused ``busy`` (nothing sent), it
    ends nothing, as its reply says (an LA's stream has no stop of its own to send)."""
    runner = build_bus(bus(simulator.port))  # not started: the test runs it
    runner.owner.open()
    la1 = runner.drivers["la1"]
    try:
        runner.streams.start(la1, la1.follow_target({"position": 1000}), now())
        runner.planner._command_limit = 0  # full
        refused = Future()
        runner._work.plan_command("la1", la1.parse('{"op":"pause"}'), None, now() + 10, refused)
        assert refused.exception(0).code == "busy"
        assert runner.streams.fed("la1")
        runner.planner._command_limit = 1
        taken = Future()
        runner._work.plan_command("la1", la1.parse('{"op":"pause"}'), None, now() + 10, taken)
        assert not taken.done() and not runner.streams.following("la1")
    finally:
        runner.owner.close()


def test_a_device_passed_between_a_command_follow_and_a_stream_keeps_its_follow_period(
    simulator,
) -> None:
    """A stream started right after a command's follow sends its first tick a follow period
    after that follow went (the bus's own times of the two writes); and once the stream
    ended, a command's follow sooner than a period after its last tick is refused."""
    runner = build_bus(bus(simulator.port, follow_period_ms=10))  # not started: the test runs it
    runner.owner.open()
    records: list[tuple] = []  # (time, direction, bytes, identifier): the owner's tap
    runner.owner.tap = records.append
    work, la1 = runner._work, runner.drivers["la1"]

    def follow_command() -> Future:
        future = Future()
        command = la1.parse('{"op":"follow","position":900}')
        work.plan_command("la1", command, None, now() + 10, future)
        return future

    def follows_to_la1() -> list[float]:
        """When each write carrying la1 a follow target went (the tap's time of it)."""
        times = []
        for at, direction, wire, _ in records:
            decoder = la.CommandDecoder()
            decoder.feed(wire)
            frame = next(decoder.events()) if direction == TX else None
            if isinstance(frame, la.GroupFollowCommand):
                frame = next((t for t in frame.targets if t.device_id == 1), None)
            if isinstance(frame, la.FollowCommand | la.Target) and frame.device_id == 1:
                times.append(at)
        return times

    try:
        command = follow_command()
        while not command.done():
            runner._step()
        runner.streams.start(la1, la1.follow_target({"position": 1000}), now())
        while len(follows_to_la1()) < 2:
            runner._step()
        command_went, first_tick = follows_to_la1()
        assert first_tick - command_went >= 0.010
        runner.streams.end("la1", "the test")
        refused = follow_command().exception(0)
        assert refused.code == "busy" and "one was sent" in str(refused)
    finally:
        runner.owner.close()


def estops_on_the_wire(simulator) -> list[int]:
    """The id of every Inspire LA e-stop frame the simulator took, in order."""
    wires = {la.encode(la.ControlCommand(i, la.ControlCode.ESTOP)).hex(): i for i in (1, 2)}
    return [wires[r.wire] for r in simulator.recorder.received() if r.wire in wires]


def step_while_stopping(runner: BusRunner) -> None:
    """Run the (not started) runner's turns until no e-stop is left to send, 10 s at most."""
    deadline = now() + 10
    while runner.planner.stopping and now() < deadline:
        runner._step()


def test_estops_put_again_and_again_send_each_frame_at_most_twice_and_answer_each(
    simulator,
) -> None:
    """A flood of e-stops (a stuck button, a hostile client) queues no more than the one on
    the line and one waiting: the wire carries each device's e-stop once for the first and
    once for all that came while it was on the line, and every one of them is answered."""
    runner = build_bus(bus(simulator.port))  # not started: the test is the bus thread
    runner.owner.open()
    try:
        handed = [runner.estop() for _ in range(50)]
        runner._drain_inbox()
        runner._step()  # la1's e-stop: the first job is on the line
        handed += [runner.estop() for _ in range(50)]
        runner._drain_inbox()
        deadline = now() + 10
        while not all(future.done() for future in handed) and now() < deadline:
            runner._step()
        assert [future.exception(0) for future in handed] == [None] * 100
        assert estops_on_the_wire(simulator) == [1, 2, 1, 2]
    finally:
        runner.owner.close()


def test_estops_while_the_bus_is_down_are_answered_at_once_and_sent_once_it_is_back(
    simulator,
) -> None:
    """Nothing holds an e-stop's caller (nor memory, however many come) while its bus is
    down: each is answered ``bus_unavailable`` at once, the devices latched, and one e-stop
    goes to them once the bus is back, ahead of everything."""
    runner = build_bus(bus(simulator.port))  # not started, not open: the test is the bus thread
    try:
        handed = [runner.estop() for _ in range(20)]
        runner._drain_inbox()
        assert {future.exception(0).code for future in handed} == {"bus_unavailable"}
        assert all(driver.estopped for driver in runner.drivers.values())
        assert runner._ensure_open()
        step_while_stopping(runner)
        assert estops_on_the_wire(simulator) == [1, 2]
    finally:
        runner.owner.close()


def test_an_estop_whose_first_frame_lost_the_link_is_answered_and_sent_once_it_is_back(
    simulator,
) -> None:
    """The link lost under an e-stop's first exchange: its callers are answered
    ``bus_unavailable``, and the e-stop goes to the devices once the bus is back (a device
    may never have had it), as one handed over while the bus was down does."""
    runner = build_bus(bus(simulator.port))  # not started: the test is the bus thread
    runner.owner.open()
    try:
        handed = runner.estop()
        runner._drain_inbox()
        slot = runner.planner.decide(now() + 1)
        assert slot.priority is Priority.ESTOP
        runner._link_lost(BusIOError("unplugged"), slot)  # as ``_execute`` on a failed write
        assert handed.exception(0).code == "bus_unavailable"
        assert runner._ensure_open()
        step_while_stopping(runner)
        assert estops_on_the_wire(simulator) == [1, 2]
    finally:
        runner.owner.close()


def test_an_estop_handed_over_while_anothers_frames_go_is_not_waited_for(simulator) -> None:
    """Rule 1: the caller waits for an e-stop's first exchange, unless another e-stop's frames
    are going already (a client putting e-stops in a loop holds its zenoh link no longer)."""
    runner = build_bus(bus(simulator.port))  # not started: the test is the bus thread
    runner.owner.open()
    try:
        runner.estop()
        assert not runner.estop_sent(0)  # handed over: its first exchange is awaited
        runner._drain_inbox()
        runner._step()  # la1's e-stop: the job is on the line
        assert runner.estop_sent(0)
        runner.estop()
        assert runner.estop_sent(0)  # la2's e-stop still to go: nothing to wait for
    finally:
        runner.owner.close()


def test_a_full_queue_answers_busy_and_a_closed_bus_unavailable(simulator) -> None:
    runner = build_bus(bus(simulator.port))  # not started: nothing drains the queue
    first, second, third = Future(), Future(), Future()
    runner._work.queue_job(Job("la1", deque([status(1)]), future=first))
    assert isinstance(first.exception(0), BusUnavailableError), "the port is not open yet"
    runner.owner.open()
    runner.planner._command_limit = 1
    runner._work.queue_job(Job("la1", deque([status(1)]), future=second))
    runner._work.queue_job(Job("la1", deque([status(1)]), future=third))
    runner.owner.close()
    assert not second.done()
    assert isinstance(third.exception(0), BusyError) and BusyError.code == "busy"
    assert runner.counters.busy_commands == 1


def test_the_link_comes_back_after_a_replug(wait_for, simulator, monkeypatch) -> None:
    """Replugged once the reconnect backoff is at its longest, the bus is back. The backoff is
    checked on its figures (the waits between attempts to open the port double from 0.1 s
    to ``BACKOFF_MAX_S`` and no further, so "back within 3 s" holds by construction),
    each shortened to 10 ms; the reconnect itself is waited for, with a generous deadline.
    The bus was up long enough before the unplug (``STABLE_S`` made 0 here): its loss is not
    one of a link that fails as it opens (``tests/test_reconnect.py``)."""
    monkeypatch.setattr(link, "STABLE_S", 0.0)
    events = []
    runner = build_bus(bus(simulator.port), on_event=events.append)
    backoffs = []  # what the bus thread would have waited between attempts to open the port
    wait = runner._stop.wait

    def quick_wait(timeout=None):
        backoffs.append(timeout)
        return wait(0.01)

    runner._stop.wait = quick_wait
    runner.start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        simulator.unplug()
        wait_for(lambda: not runner.drivers["la1"].online)
        wait_for(lambda: len(backoffs) >= 8)
        simulator.replug()
        wait_for(lambda: runner.drivers["la1"].online, timeout=10)
        doubling = [BACKOFF_FIRST_S * 2**i for i in range(5)]  # 0.1 s … 1.6 s
        assert backoffs[:5] == doubling and set(backoffs[5:]) == {BACKOFF_MAX_S}
        assert runner.statistics().reconnects == 1
        kinds = [e.type for e in events if e.device == "la1"]
        assert kinds.count("offline") == 1 and kinds.count("online") == 2
    finally:
        runner.stop()


def test_a_bug_in_a_driver_does_not_leave_the_bus_without_its_thread(wait_for, simulator) -> None:
    runner = build_bus(bus(simulator.port)).start()
    try:
        wait_for(lambda: all(d.online for d in runner.drivers.values()))
        driver = runner.drivers["la1"]
        original, calls = driver.apply, []

        def broken(*arguments):
            calls.append(1)
            if len(calls) == 1:
                raise RuntimeError("a driver bug")
            return original(*arguments)

        driver.apply = broken
        wait_for(lambda: len(calls) >= 2 and driver.online)
        assert runner.alive and runner.statistics().reconnects == 1
    finally:
        runner.stop()


def test_an_unexpected_error_closes_the_bus_for_a_pause_never_a_spin(monkeypatch, simulator):
    """A bug in the bus thread (here: an open that raises what no owner should) is logged and
    the bus opened again ``UNEXPECTED_PAUSE_S`` later: a config python-can refused with a
    TypeError made 35,000 tracebacks in 5 s at a full core before the pause."""
    runner = build_bus(bus(simulator.port))
    attempts: list[float] = []

    def open_with_a_bug() -> None:
        attempts.append(now())
        raise RuntimeError("a bug")

    monkeypatch.setattr(runner.owner, "open", open_with_a_bug)
    monkeypatch.setattr(runner_module, "UNEXPECTED_PAUSE_S", 0.2)
    runner.start()
    time.sleep(0.5)
    runner.stop(5.0)
    assert 1 <= len(attempts) <= 4
    assert all(b - a >= 0.2 for a, b in itertools.pairwise(attempts))
