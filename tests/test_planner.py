"""The bus planner's timing rules, with a fake clock: gap, precedence, follow slots, bounded
queues, retries. Times are plain floats; nothing sleeps."""

from __future__ import annotations

from collections import deque

import pytest

from busgate.codecs.framing import ExpectedReply
from busgate.codecs.timing import uart_time
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_state import Mode, Settings
from busgate.gateway.scheduler.planner import (
    CLIENT_SHARE,
    EVERY_DEVICE,
    MAX_RETRIES,
    BusPlanner,
    Job,
    Priority,
    Slot,
)
from busgate.gateway.scheduler.polling import DevicePoller
from busgate.gateway.scheduler.tickers import FollowTicker
from tests.stand_in_driver import StandInDriver

GAP = 0.001
TIMING = link_timing("inspire_la", 921_600, margin_s=0.0, gap_s=GAP)


def status_request(device_id: int = 1, *, idempotent: bool = True) -> Request:
    """A 9-byte frame answered by a 22-byte reply (an LA status query's shape)."""
    return Request(("status", device_id), b"\x00" * 9, ExpectedReply(device_id, 22, (object,)),
                   idempotent)


def silent_request(size: int = 9) -> Request:
    return Request(("broadcast", size), b"\x00" * size, None)


WORST = TIMING.worst_case(status_request())


class Poller:
    def __init__(self, device: str, period_s: float, next_due: float = 0.0) -> None:
        self.device, self.period_s, self.next_due = device, period_s, next_due
        self.built = self.withdrawals = 0

    def build(self) -> list[Request]:
        self.built += 1
        return [status_request()]

    def withdrawn(self) -> None:
        self.withdrawals += 1


class FollowingDriver(StandInDriver):
    """The least driver a follow ticker needs: it coalesces targets into one frame."""

    follow_group_limit = 2

    @classmethod
    def follow_request(cls, targets):
        return silent_request(3 + 3 * len(targets))


def ticker_at(planner: BusPlanner, now: float, period: float = 0.010) -> FollowTicker:
    ticker = FollowTicker(FollowingDriver, period, BusCounters(0.0), on_stale=lambda d: None)
    ticker.update(FollowingDriver("la1", 1), 1000, now)
    planner.tickers.append(ticker)
    return ticker


def run(planner: BusPlanner, slot: Slot, start: float, duration: float, *, failed=False):
    """Pretend the runner carried out ``slot`` from ``start`` for ``duration``."""
    if not isinstance(slot.source, Job):
        slot.source.sent(start)
    return planner.finished(slot, start + duration, failed=failed)


def test_worst_case_is_frame_plus_reply_time_plus_reply():
    assert pytest.approx(uart_time(9, 921_600) + 800e-6 + uart_time(22, 921_600)) == WORST
    assert TIMING.worst_case(silent_request()) == pytest.approx(uart_time(9, 921_600))


def test_nothing_starts_within_the_gap_after_the_line_went_idle():
    planner = BusPlanner(TIMING)
    planner.push_command(Job("la1", deque([status_request(), status_request()])))
    first = planner.decide(0.0)
    assert isinstance(first, Slot)
    run(planner, first, 0.0, 0.0012)
    assert planner.decide(0.0012 + GAP / 2) == pytest.approx(0.0012 + GAP)
    assert isinstance(planner.decide(0.0012 + GAP), Slot)


def test_precedence_estop_then_commands_then_polls():
    planner = BusPlanner(TIMING)
    planner.pollers = [Poller("la2", 0.05)]
    command = Job("la1", deque([status_request(1)]))
    estop = Job("*", deque([silent_request()]))
    planner.push_command(command)
    planner.push_estop(estop)
    order = []
    t = 0.0
    for _ in range(3):
        slot = planner.decide(t)
        assert isinstance(slot, Slot)
        order.append(slot.priority)
        run(planner, slot, t, 0.001)
        t += 0.001 + GAP
    assert order == [Priority.ESTOP, Priority.COMMAND, Priority.POLL]


class ProbePoller(Poller):
    """An offline device's probe: two frames, decided from what the test says the gateway
    knows when they are built (an ``init`` that releases a motor nobody enabled)."""

    def __init__(self, device: str) -> None:
        super().__init__(device, 0.25)
        self.enabled = False

    def build(self) -> list[Request]:
        self.built += 1
        return [] if self.enabled else [status_request(), silent_request(5)]


def _sent(planner: BusPlanner, t: float, steps: int) -> list[tuple[str, object]]:
    """The device and frame of each of the next ``steps`` exchanges, a millisecond each,
    each asked for a little past the gap after the one before."""
    sent = []
    for _ in range(steps):
        slot = planner.decide(t)
        assert isinstance(slot, Slot), slot
        sent.append((slot.source.device, slot.request.frame))
        run(planner, slot, t, 0.001)
        t += 0.001 + GAP + 0.0001
    return sent


def test_a_devices_job_that_started_runs_to_its_end_before_its_next_starts():
    """Rule 8: another device's command goes between a probe's frames, the probed device's
    own (an enable: the probe's release would undo it) waits for their end."""
    planner = BusPlanner(TIMING)
    planner.pollers = [ProbePoller("la1")]
    assert _sent(planner, 0.0, 1) == [("la1", ("status", 1))]
    planner.push_command(Job("la1", deque([silent_request(7)])))
    planner.push_command(Job("la2", deque([status_request(2)])))
    assert _sent(planner, 0.002, 3) == [
        ("la2", ("status", 2)), ("la1", ("broadcast", 5)), ("la1", ("broadcast", 7))]


def test_a_devices_poll_is_built_after_its_waiting_commands_even_when_built_before():
    """Rule 8: a probe due while the device's command waits is decided after it (the enable
    it brought: nothing to release); one built before a command came, not started, gives way
    to it and is built again after it."""
    planner = BusPlanner(TIMING)
    probe = ProbePoller("la1")
    planner.pollers = [probe]
    planner.push_command(Job("la1", deque([silent_request(7)])))
    assert _sent(planner, 0.0, 1) == [("la1", ("broadcast", 7))]
    assert probe.built == 0
    probe.enabled = True  # what the command did
    assert planner.decide(0.002) == pytest.approx(0.25)  # built then: nothing to send
    assert probe.built == 1

    planner, probe = BusPlanner(TIMING), ProbePoller("la1")
    planner.pollers = [probe]
    planner.push_command(Job("la2", deque([status_request(2)])))
    assert _sent(planner, 0.0, 1) == [("la2", ("status", 2))]  # the probe is built meanwhile
    planner.push_command(Job("la1", deque([silent_request(7)])))
    assert _sent(planner, 0.002, 1) == [("la1", ("broadcast", 7))]
    assert (probe.built, probe.withdrawals) == (1, 1)
    probe.enabled = True  # what the command did
    assert planner.decide(0.0045) == pytest.approx(0.252)  # built again, due since 0.002: empty
    assert probe.built == 2


def test_a_poll_that_waits_for_room_before_a_tick_never_holds_its_devices_command():
    """Rule 8 with a follow stream: a poll built, too long to fit between two ticks, gives
    way to a short command of its device, which goes in the room the poll could not use."""
    planner = BusPlanner(TIMING)
    ticker_at(planner, now=0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    long_poll = Poller("la2", 0.05, next_due=0.0)
    long_poll.build = lambda: [silent_request(2000)]  # never fits in 10 ms
    planner.pollers = [long_poll]
    assert planner.decide(0.002) == pytest.approx(0.010)  # built; it waits for room
    planner.push_command(Job("la2", deque([status_request(2)])))
    slot = planner.decide(0.002)
    assert isinstance(slot, Slot) and slot.request.frame == ("status", 2)
    assert long_poll.withdrawals == 1 and long_poll.next_due == pytest.approx(0.002)


def test_an_estop_gives_back_what_the_polls_it_drops_handed_out():
    planner = BusPlanner(TIMING)
    planner.pollers = [Poller("la1", 0.05, next_due=0.0), Poller("la2", 0.05, next_due=1.0)]
    planner.push_command(Job("la3", deque([silent_request(7)])))
    planner.decide(0.0)  # la1's poll built
    planner.drop_commands()
    assert [p.withdrawals for p in planner.pollers] == [1, 0]


def test_a_job_for_every_device_waits_for_each_started_job_and_holds_the_later_ones():
    """Rule 8 for a reset of the whole bus (one job, ``EVERY_DEVICE``): an outside audit saw
    it go between an offline drive's probe frames, whose release then undid the reset's
    enable. A command that came after it waits for it, and no poll is decided meanwhile."""
    planner = BusPlanner(TIMING)
    later = Poller("la3", 0.05, next_due=0.0015)
    planner.pollers = [ProbePoller("la1"), later]
    assert _sent(planner, 0.0, 1) == [("la1", ("status", 1))]
    planner.push_command(Job(EVERY_DEVICE, deque([silent_request(7), silent_request(8)])))
    planner.push_command(Job("la2", deque([status_request(2)])))
    assert _sent(planner, 0.002, 3) == [
        ("la1", ("broadcast", 5)), (EVERY_DEVICE, ("broadcast", 7)),
        (EVERY_DEVICE, ("broadcast", 8))]
    assert later.built == 0  # due meanwhile: decided once the reset went
    assert _sent(planner, 0.0085, 2) == [("la2", ("status", 2)), ("la3", ("status", 1))]
    assert later.built == 1


def test_a_poll_held_behind_its_devices_command_does_not_wake_the_planner_early():
    """The command waits for room before a tick; the poll it holds back is no reason to ask
    again before then (it is built once the command is done)."""
    planner = BusPlanner(TIMING)
    ticker_at(planner, now=0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    planner.pollers = [Poller("la2", 0.05, next_due=0.0)]
    planner.push_command(Job("la2", deque([silent_request(2000)])))  # never fits in 10 ms
    assert planner.decide(0.002) == pytest.approx(0.010)


def test_a_due_tick_goes_first_and_nothing_starts_that_would_make_it_late():
    planner = BusPlanner(TIMING)
    ticker = ticker_at(planner, now=0.0)
    tick = planner.decide(0.0)
    assert isinstance(tick, Slot) and tick.priority is Priority.FOLLOW
    run(planner, tick, 0.0, uart_time(6, 921_600))
    planner.push_command(Job("la1", deque([status_request()])))
    # Just before the next tick there is no room for a worst-case exchange plus the gap.
    late = 0.010 - WORST - GAP + 1e-6
    assert planner.decide(late) == pytest.approx(0.010)
    assert ticker.next_due() == pytest.approx(0.010)
    # With room, the command goes.
    early = 0.010 - WORST - GAP - 1e-6
    slot = planner.decide(early)
    assert isinstance(slot, Slot) and slot.priority is Priority.COMMAND


def test_a_late_tick_is_not_made_up_by_a_burst():
    planner = BusPlanner(TIMING)
    ticker = ticker_at(planner, now=0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    # The host stalls: the next tick goes out 7 ms late.
    run(planner, planner.decide(0.017), 0.017, 0.0001)
    assert ticker.next_due() == pytest.approx(0.027), "one period after the late tick"
    intervals = ticker.counters.snapshot(1.0)
    assert intervals.follow_intervals == 1
    assert intervals.follow_error_p50_s == pytest.approx(0.007)


def test_streams_go_stale_and_the_ticker_falls_idle():
    planner = BusPlanner(TIMING)
    stale = []
    ticker = FollowTicker(FollowingDriver, 0.010, BusCounters(0.0), on_stale=stale.append)
    driver = FollowingDriver("la1", 1)
    ticker.update(driver, 5, 0.0)
    planner.tickers.append(ticker)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    assert ticker.fresh_s == pytest.approx(0.1), "max(3 periods, 100 ms)"
    assert planner.decide(0.2) == float("inf")
    assert stale == [driver] and ticker.next_due() is None


def test_a_stream_ends_when_its_device_follows_the_other_kind_and_a_new_one_starts():
    """A ZLAC706 follows speeds in velocity mode and positions in absolute position mode: a
    speed stream whose wheel was switched to position mode ends before its next tick (its
    300 rpm would go out as position 300), and the next target starts a stream of positions
    from the wheel's position target."""
    stale = []
    ticker = FollowTicker(Zlac706CanDriver, 0.010, BusCounters(0.0), on_stale=stale.append)
    wheel = Zlac706CanDriver("w", 1)
    wheel.machine.settings = Settings(mode=Mode.VELOCITY, enabled=True, speed_raw=0)
    ticker.update(wheel, 300.0, 0.0)
    assert str(ticker.build(0.0).wire) == "001#00fa001100000333"  # 300 rpm
    ticker.sent(0.0)
    wheel.machine.settings = Settings(mode=Mode.POSITION, relative=False, enabled=True,
                                      target_position=-40)  # fmt: skip
    assert ticker.build(0.01) is None and stale == [wheel] and not ticker.streams
    ticker.update(wheel, 300.0, 0.01)
    assert ticker.streams["w"].limiter.follows == "position"
    assert str(ticker.build(0.02).wire) == "001#00fa00160000012c"  # position 300
    ticker.update(wheel, 500.0, 0.021)  # the same kind: the stream goes on
    wheel.machine.settings = Settings(mode=Mode.VELOCITY, enabled=True)
    ticker.update(wheel, 20.0, 0.022)  # another kind: a new stream, from 0 rpm
    assert ticker.streams["w"].limiter.follows == "velocity"
    assert ticker.streams["w"].limiter.value == 0.0 and stale == [wheel, wheel]


def test_coalescing_respects_the_group_limit():
    ticker = FollowTicker(FollowingDriver, 0.010, BusCounters(0.0), on_stale=lambda d: None)
    drivers = [FollowingDriver(f"la{i}", i) for i in range(1, 4)]
    ticker.update(drivers[0], 1, 0.0)
    ticker.update(drivers[1], 2, 0.0)
    assert not ticker.has_room(drivers[2]) and ticker.has_room(drivers[0])
    assert ticker.build(0.0).wire == b"\x00" * 9, "two targets in one frame"


def test_polls_are_never_queued_and_overdue_polls_are_skipped_and_counted():
    planner = BusPlanner(TIMING)
    poller = Poller("la1", 0.010)
    planner.pollers = [poller]
    slot = planner.decide(0.0)
    assert slot.priority is Priority.POLL
    run(planner, slot, 0.0, 0.001)
    assert planner.decide(0.003) == pytest.approx(0.010), "next poll due a period later"
    slot = planner.decide(0.055)  # the host stalled for several periods
    assert isinstance(slot, Slot) and poller.built == 2 and planner.skipped_polls == 1
    assert poller.next_due == pytest.approx(0.065)


def test_command_queue_is_bounded():
    planner = BusPlanner(TIMING, command_queue=2)
    assert planner.push_command(Job("a", deque([status_request()])))
    assert planner.push_command(Job("b", deque([status_request()])))
    assert not planner.push_command(Job("c", deque([status_request()])))
    assert planner.queued == 2
    assert len(planner.drop_commands()) == 2 and planner.queued == 0


def test_one_clients_flood_takes_its_share_of_the_queue_and_leaves_room_for_the_others():
    """A client putting moves at 2,000 a second kept the queue full: every other client's
    command on that bus was answered busy."""
    planner = BusPlanner(TIMING)
    for _ in range(CLIENT_SHARE):
        assert planner.push_command(Job("la1", deque([status_request()]), client="flood"))
    assert not planner.push_command(Job("la1", deque([status_request()]), client="flood"))
    assert planner.share_taken("flood") and not planner.share_taken("arm-ctl")
    assert planner.push_command(Job("la2", deque([status_request()]), client="arm-ctl"))
    assert planner.push_command(Job("la2", deque([status_request()]), client=""))  # anonymous
    assert planner.push_command(Job("la2", deque([status_request()])))  # the gateway's own
    assert planner.queued == CLIENT_SHARE + 3


def test_an_estops_drop_keeps_the_commands_that_only_read_in_their_order():
    planner = BusPlanner(TIMING)
    jobs = [Job(f"la{n}", deque([status_request(n)]), reads_only=n % 2 == 1) for n in range(4)]
    for job in jobs:
        assert planner.push_command(job)
    dropped = planner.drop_commands(keep_reads=True)
    assert [job.device for job in dropped] == ["la0", "la2"]
    assert planner.queued == 2
    assert [job.device for job in planner.drop_commands()] == ["la1", "la3"]  # a lost link's
    assert planner.queued == 0


def test_a_stop_of_the_gateways_own_is_queued_however_full_the_queue():
    planner = BusPlanner(TIMING, command_queue=2)
    for client in ("a", "b"):
        assert planner.push_command(Job("la1", deque([status_request()]), client=client))
    planner.push_stop(Job("la2", deque([status_request(2)])))
    assert planner.queued == 3
    assert [job.device for job in planner.drop_commands()] == ["la1", "la1", "la2"]


def test_idempotent_requests_are_retried_at_most_twice_then_the_job_fails():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([status_request(), status_request(2)]))
    planner.push_command(job)
    t = 0.0
    for attempt in range(MAX_RETRIES + 1):
        slot = planner.decide(t)
        assert slot.source is job and slot.request == status_request()
        outcome = run(planner, slot, t, WORST, failed=True)
        t += WORST + GAP
        assert (outcome is job) == (attempt == MAX_RETRIES)
    assert planner.decide(t) == float("inf"), "the failed job's other request is dropped"


def test_other_requests_are_sent_once():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([status_request(idempotent=False)]))
    planner.push_command(job)
    assert run(planner, planner.decide(0.0), 0.0, WORST, failed=True) is job


def test_an_estop_goes_on_to_the_next_device_when_one_is_silent():
    planner = BusPlanner(TIMING)
    estop = Job("*", deque([status_request(1, idempotent=False), status_request(2)]),
                keep_going=True)
    planner.push_estop(estop)
    assert run(planner, planner.decide(0.0), 0.0, WORST, failed=True) is None
    slot = planner.decide(WORST + GAP)
    assert slot.request == status_request(2)
    assert run(planner, slot, WORST + GAP, WORST) is estop


def test_an_estop_joins_the_one_waiting_not_started_and_queues_behind_one_on_the_line():
    """Rule 4: e-stops put again and again wait at most one behind the one on the line; the
    one waiting sends the latest one's frames, never another copy of them."""
    planner = BusPlanner(TIMING)
    first = Job("*", deque([status_request(1), status_request(2)]), keep_going=True)
    assert planner.push_estop(first) is first
    assert planner.push_estop(Job("*", deque([status_request(3)]))) is first
    assert list(first.requests) == [status_request(3)]
    first.requests = deque([status_request(1), status_request(2)])
    t = 0.0
    run(planner, planner.decide(t), t, WORST)  # the first job started: new ones wait behind
    second = Job("*", deque([status_request(4)]))
    assert planner.push_estop(second) is second
    for device_id in range(5, 105):
        assert planner.push_estop(Job("*", deque([status_request(device_id)]))) is second
    sent = []
    while isinstance(slot := planner.decide(t := t + WORST + GAP), Slot):
        sent.append(slot.request)
        run(planner, slot, t, WORST)
    assert sent == [status_request(2), status_request(104)]


def test_a_short_poll_may_use_the_room_before_a_tick_a_long_command_cannot():
    planner = BusPlanner(TIMING)
    ticker_at(planner, now=0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    long_write = Request("w", b"\x00" * 200, ExpectedReply(1, 22, (object,)))
    planner.push_command(Job("la1", deque([long_write])))
    planner.pollers = [Poller("la2", 0.05, next_due=0.0)]
    now = 0.010 - TIMING.worst_case(long_write) - GAP + 1e-4
    slot = planner.decide(now)
    assert isinstance(slot, Slot) and slot.priority is Priority.POLL


def test_after_a_timeout_only_frames_without_reply_go_until_the_holdoff_ends():
    planner = BusPlanner(TIMING)
    planner.hold_replies_until = 0.010
    planner.push_command(Job("la1", deque([status_request()])))
    assert planner.decide(0.0) == pytest.approx(0.010)
    planner.push_estop(Job("*", deque([silent_request()])))
    assert planner.decide(0.0).priority is Priority.ESTOP
    assert isinstance(planner.decide(0.010), Slot)


def test_a_command_not_started_by_its_deadline_is_dropped_never_sent():
    planner = BusPlanner(TIMING)
    late = Job("la1", deque([status_request(1)]), start_by=0.5)
    in_time = Job("la2", deque([status_request(2)]), start_by=2.0)
    planner.push_command(late)
    planner.push_command(in_time)
    slot = planner.decide(1.0)
    assert slot.source is in_time, "the expired command is skipped, the next one goes"
    assert planner.take_expired() == [late] and planner.take_expired() == []
    run(planner, slot, 1.0, WORST)
    assert planner.decide(1.0 + WORST + GAP) == float("inf"), "nothing else is left to send"


def test_a_started_command_runs_to_its_end_past_its_deadline():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([status_request(1), status_request(1)]), start_by=0.5)
    planner.push_command(job)
    run(planner, planner.decide(0.4), 0.4, WORST)
    slot = planner.decide(1.0)
    assert slot.source is job and planner.take_expired() == []


def test_a_scan_waits_behind_commands_and_due_polls_and_expires_as_a_whole():
    planner = BusPlanner(TIMING)
    planner.pollers = [Poller("la2", 0.05)]
    scan = Job("*", deque([status_request(i, idempotent=False) for i in (3, 4, 5)]),
               keep_going=True, outcomes=[], start_by=1.0, scan=True)
    command = Job("la1", deque([status_request(1)]))
    planner.push_command(scan)
    planner.push_command(command)
    order, t = [], 0.0
    for _ in range(3):
        slot = planner.decide(t)
        order.append(slot.source)
        run(planner, slot, t, WORST)
        t += WORST + GAP
    assert order[0] is command and order[1].priority is Priority.POLL and order[2] is scan
    slot = planner.decide(1.5)
    assert planner.take_expired() == [scan], "past its deadline, even once started"
    assert slot.priority is Priority.POLL
    run(planner, slot, 1.5, WORST)
    assert not isinstance(planner.decide(1.5 + WORST + GAP), Slot), "no probe is left"


def test_an_estop_goes_ahead_of_a_follow_tick_that_is_due():
    planner = BusPlanner(TIMING)
    ticker_at(planner, now=0.0)
    planner.push_estop(Job("*", deque([silent_request()])))
    slot = planner.decide(0.0)
    assert slot.priority is Priority.ESTOP


def test_a_tick_built_and_put_off_does_not_move_its_streams_limiter_on() -> None:
    """A stream's step is per tick on the wire: built twice (the first put off), the second
    frame carries the first's target, not two steps' worth (``tickers`` rule 6)."""
    from busgate.gateway.drivers.inspire_la import InspireLaDriver
    from busgate.schemas.inspire_la import JOINT
    from busgate.schemas.joints import Joint, JointTable

    driver = InspireLaDriver("la1", 1)
    table = JointTable.model_validate({"unit": "m", "scale": 5e-6, "max_velocity": 0.01})
    driver.joint = Joint.of("la1", JOINT, table)  # 40 counts a 20 ms tick
    ticker = FollowTicker(InspireLaDriver, 0.020, BusCounters(0.0), on_stale=lambda d: None)
    ticker.update(driver, 2000, 0.0)
    stream = ticker.streams["la1"]
    stream.limiter.value = 0  # commanded at 0
    first = ticker.build(0.0)
    again = ticker.build(0.001)  # the first was never sent
    assert again.wire == first.wire
    ticker.sent(0.001)
    assert ticker.build(0.021).wire != first.wire
    assert stream.limiter.value == pytest.approx(80)  # two ticks on the wire, 40 counts each


def test_a_device_poller_gives_back_the_restore_of_a_poll_taken_out_unsent():
    """A rebooted device's settings go with its next poll; that poll taken out unsent (its
    device's command came first, an e-stop) leaves them due, and a plain poll's does not."""
    driver = StandInDriver("la1", 1)
    driver.online = True
    driver.applied_settings = {7: silent_request(7)}
    poller = DevicePoller(driver, 20.0, start=0.0)
    poller.build()  # its first: its init
    driver.restore_pending = True
    assert poller.build() == [silent_request(7)]
    assert not driver.restore_pending
    poller.withdrawn()
    assert driver.restore_pending
    assert poller.build() == [silent_request(7)]
    assert poller.build() == []  # a plain poll: nothing to give back
    poller.withdrawn()
    assert not driver.restore_pending


def test_a_group_frame_is_a_job_of_each_device_it_moves():
    """Rule 8 for a group move, queued under its first device: another device it moves has
    no poll built while it waits, and a stop of that device sent after it waits for it (left
    behind a tick, the group frame went after the stop and moved that device again)."""
    planner = BusPlanner(TIMING)
    ticker_at(planner, now=0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    poll = Poller("la2", 0.05, next_due=0.0)
    planner.pollers = [poll]
    group = silent_request(500)  # 5.4 ms: it fits only early between two ticks
    planner.push_command(Job("la1", deque([group]), also_moves=("la2",)))
    assert planner.decide(0.005) == pytest.approx(0.010)
    assert poll.built == 0
    planner.push_command(Job("la2", deque([silent_request(9)])))
    assert planner.decide(0.005) == pytest.approx(0.010)
    run(planner, planner.decide(0.010), 0.010, 0.0001)  # the tick
    assert _sent(planner, 0.0112, 2) == [("la1", ("broadcast", 500)), ("la2", ("broadcast", 9))]


class Greeted(StandInDriver):
    """Its init and its poll told apart."""

    def init(self) -> list:
        return [silent_request(1)]

    def poll(self) -> list:
        return [silent_request(2)]


def test_a_device_online_before_its_first_poll_is_sent_its_init_first():
    """A device that reports unasked (a ZLAC706's heartbeats) can be online before its first
    poll is built, and was then polled, never sent its init: an audit saw the demo's base
    wheels never released at start (the ZLAC706's init). Its init goes first, and again if
    that poll is taken out unsent; then it is polled."""
    driver = Greeted("w", 1)
    driver.online = True
    poller = DevicePoller(driver, 20.0, start=0.0)
    assert poller.build() == [silent_request(1)]
    poller.withdrawn()
    assert poller.build() == [silent_request(1)]
    assert poller.build() == [silent_request(2)]
    poller.withdrawn()
    assert poller.build() == [silent_request(2)]
