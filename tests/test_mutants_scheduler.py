"""The scheduler's rules that mutation testing (``python tools/mutation/run.py scheduler``) found
untested: retries and deadlines, poll order and skips, boundaries of the follow slot and the
reply holdoff, ticks that restart after a pause, and the follow streams' lifecycle (which
ticker carries a stream, what its end sends). Pure calls on a fake clock; nothing sleeps."""

from __future__ import annotations

import math
from collections import deque

import pytest

from busgate.codecs.framing import ExpectedReply
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.scheduler.limiter import StreamLimiter
from busgate.gateway.scheduler.planner import (
    COMMAND_QUEUE,
    MAX_RETRIES,
    BusPlanner,
    Job,
    Priority,
    Slot,
)
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.tickers import FollowStream, FollowTicker, KeepaliveTicker, commanded
from busgate.schemas import inspire_la, zlac706
from busgate.schemas.joints import Joint, JointTable
from tests.stand_in_driver import StandInDriver

GAP = 0.001
TIMING = link_timing("inspire_la", 921_600, margin_s=0.0, gap_s=GAP)


def asking(device_id: int = 1, *, idempotent: bool = True) -> Request:
    """A request answered by a reply (an LA status query's shape)."""
    return Request(
        ("status", device_id), b"\x00" * 9, ExpectedReply(device_id, 22, (object,)), idempotent
    )


def silent(tag: object = "broadcast", size: int = 9) -> Request:
    return Request(tag, b"\x00" * size, None)


class Poller:
    def __init__(self, device: str, period_s: float, next_due: float = 0.0) -> None:
        self.device, self.period_s, self.next_due = device, period_s, next_due

    def build(self) -> list[Request]:
        return [asking()]


class Follower(StandInDriver):
    """A driver whose follow frame spells out its targets, so a test can read what a tick
    carries; its stale stream asks for a stop."""

    follow_group_limit = 2

    @classmethod
    def follow_request(cls, targets):
        return silent(("follow", tuple((d.name, t) for d, t in targets)))

    def stale_stream(self) -> list[Request]:
        return [silent(("stop", self.name))]


class OtherFollower(Follower):
    kind = "other"


def run(planner: BusPlanner, slot: Slot, start: float, duration: float, *, failed=False):
    """Pretend the runner carried out ``slot`` from ``start`` for ``duration``."""
    if not isinstance(slot.source, Job):
        slot.source.sent(start)
    return planner.finished(slot, start + duration, failed=failed)


def ticker(period: float = 0.010) -> FollowTicker:
    return FollowTicker(Follower, period, BusCounters(0.0), on_stale=lambda d: None)


# -- the planner -----------------------------------------------------------------------------


def test_a_command_may_still_start_at_its_deadline():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([asking()]), start_by=1.0)
    planner.push_command(job)
    slot = planner.decide(1.0)
    assert isinstance(slot, Slot) and slot.source is job and planner.take_expired() == []


def test_a_job_being_retried_has_started_and_runs_to_its_end_past_its_deadline():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([asking()]), start_by=0.5)
    planner.push_command(job)
    assert run(planner, planner.decide(0.4), 0.4, 0.01, failed=True) is None, "retried"
    slot = planner.decide(1.0)
    assert isinstance(slot, Slot) and slot.source is job, "the retry goes, late as it is"
    assert planner.take_expired() == []


def test_each_request_of_a_job_gets_its_own_retries():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([asking(1), asking(2)]))
    planner.push_command(job)
    t = 0.0
    assert run(planner, planner.decide(t), t, 0.01, failed=True) is None  # first one retried
    t += 0.02
    assert run(planner, planner.decide(t), t, 0.01) is None  # ... and answered
    for attempt in range(MAX_RETRIES + 1):  # the second one fails every time
        t += 0.02
        slot = planner.decide(t)
        assert slot.request == asking(2)
        outcome = run(planner, slot, t, 0.01, failed=True)
        assert (outcome is job) == (attempt == MAX_RETRIES)


def test_a_due_tick_carries_its_ticker_frame():
    planner = BusPlanner(TIMING)
    follow = ticker()
    follow.update(Follower("la1", 1), 7, 0.0)
    planner.tickers.append(follow)
    slot = planner.decide(0.0)
    assert slot.priority is Priority.FOLLOW and slot.source is follow
    assert slot.request.frame == ("follow", (("la1", 7),))


def test_the_reply_holdoff_ends_at_its_moment():
    planner = BusPlanner(TIMING)
    planner.hold_replies_until = 0.5
    planner.push_command(Job("la1", deque([asking()])))
    assert planner.decide(0.25) == 0.5
    assert isinstance(planner.decide(0.5), Slot)


def test_during_the_holdoff_a_silent_command_passes_one_waiting_for_its_reply():
    planner = BusPlanner(TIMING)
    planner.hold_replies_until = 0.5
    planner.push_command(Job("la1", deque([asking()])))
    broadcast = Job("la2", deque([silent()]))  # another device's: la1's own would wait
    planner.push_command(broadcast)
    slot = planner.decide(0.0)
    assert isinstance(slot, Slot) and slot.source is broadcast


class TickAt:
    """A ticker whose next tick is due at a moment the test chose."""

    period_s = 0.010

    def __init__(self, due: float) -> None:
        self.due = due

    def next_due(self) -> float:
        return self.due


def test_an_exchange_that_ends_a_slack_before_the_tick_exactly_still_fits():
    planner = BusPlanner(TIMING)
    request = asking()
    now = 0.5
    planner.tickers.append(TickAt(now + TIMING.worst_case(request) + planner.slack_s))
    planner.push_command(Job("la1", deque([request])))
    slot = planner.decide(now)
    assert isinstance(slot, Slot) and slot.priority is Priority.COMMAND


def test_tickers_due_together_go_in_the_order_they_were_opened():
    planner = BusPlanner(TIMING)
    first, second = ticker(), ticker()
    first.update(Follower("la1", 1), 1, 0.0)
    second.update(Follower("la3", 3), 3, 0.0)
    planner.tickers += [first, second]
    assert planner.decide(0.0).source is first


def test_the_poll_whose_next_period_comes_first_goes_first():
    planner = BusPlanner(TIMING)
    slow, fast = Poller("slow", 0.5, next_due=0.25), Poller("fast", 0.125, next_due=0.0)
    planner.pollers = [slow, fast]
    slot = planner.decide(0.25)
    assert slot.priority is Priority.POLL and slot.source.device == "fast"


def test_a_poll_is_started_even_when_a_poller_before_it_is_not_due():
    planner = BusPlanner(TIMING)
    planner.pollers = [Poller("later", 0.5, next_due=0.25), Poller("now", 0.5, next_due=0.0)]
    slot = planner.decide(0.0)
    assert slot.priority is Priority.POLL and slot.source.device == "now"


def test_each_period_a_waiting_poll_misses_is_counted_once_and_others_still_start():
    planner = BusPlanner(TIMING)
    planner.hold_replies_until = 10.0  # polls wait for replies: none goes out
    held = Poller("held", 0.25, next_due=0.0)
    planner.pollers = [held]
    planner.decide(0.0)  # its poll is made and waits
    planner.decide(0.25)  # a whole period: skipped
    planner.decide(0.5)  # and another
    assert planner.skipped_polls == 2 and held.next_due == 0.75
    other = Poller("other", 0.25, next_due=0.5)
    planner.pollers.append(other)
    planner.decide(0.75)
    assert other.next_due == 0.75, "the poller after the waiting one started its poll"
    assert planner.skipped_polls == 3


def test_polls_on_time_are_not_counted_as_skipped_and_each_stall_counts():
    planner = BusPlanner(TIMING)
    poller = Poller("la1", 0.25, next_due=1000.0)
    planner.pollers = [poller]
    t = 1000.0
    for _ in range(3):  # punctual, late in the clock's life
        slot = planner.decide(t)
        assert slot.priority is Priority.POLL
        run(planner, slot, t, 0.01)
        t += 0.25
    assert planner.skipped_polls == 0
    for stall in (1.0, 2.0):  # the host stalls twice, several periods each time
        t += stall
        run(planner, planner.decide(t), t, 0.01)
        assert poller.next_due == t + 0.25
    assert planner.skipped_polls == 2


def test_scans_start_one_after_the_other():
    planner = BusPlanner(TIMING)
    follow = ticker()
    follow.update(Follower("la1", 1), 7, 0.0)
    planner.tickers.append(follow)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    long_probe = Request("probe", b"\x00" * 200, ExpectedReply(3, 22, (object,)))
    first = Job("*", deque([long_probe]), keep_going=True, scan=True)
    second = Job("*", deque([asking(4)]), keep_going=True, scan=True)
    planner.push_command(first)
    planner.push_command(second)
    now = 0.010 - TIMING.worst_case(asking()) - planner.slack_s - 1e-4  # room for a short one
    assert not isinstance(planner.decide(now), Slot), "the second scan does not jump the first"


# -- follow tickers --------------------------------------------------------------------------


def test_a_new_target_replaces_the_one_the_next_tick_carries():
    follow = ticker()
    driver = Follower("la1", 1)
    follow.update(driver, 5, 0.0)
    follow.update(driver, 6, 0.005)
    assert follow.build(0.005).frame == ("follow", (("la1", 6),))


def test_a_stream_stays_while_fresh_to_the_limit_late_in_the_clocks_life():
    follow = ticker()
    follow.update(Follower("la1", 1), 5, 1000.0)
    assert follow.build(1000.0) is not None
    assert follow.fresh_s == 0.1
    follow.update(Follower("la1", 1), 5, 0.0)
    assert follow.build(0.1) is not None, "a target exactly fresh_s old still holds"


def test_a_stream_stopped_leaves_no_tick_to_make_room_for():
    planner = BusPlanner(TIMING)
    follow = ticker()
    follow.update(Follower("la1", 1), 5, 0.0)
    planner.tickers.append(follow)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    follow.stop("la1")
    assert follow.next_due() is None
    long_write = Request("w", b"\x00" * 200, ExpectedReply(1, 22, (object,)))
    planner.push_command(Job("la1", deque([long_write])))
    assert isinstance(planner.decide(0.005), Slot), "no tick is due any more"


def test_a_ticker_that_went_idle_restarts_at_once_and_the_pause_is_not_an_interval():
    planner = BusPlanner(TIMING)
    stale = []
    follow = FollowTicker(Follower, 0.010, BusCounters(0.0), on_stale=stale.append)
    driver = Follower("la1", 1)
    follow.update(driver, 5, 1000.0)
    planner.tickers.append(follow)
    run(planner, planner.decide(1000.0), 1000.0, 0.0001)
    run(planner, planner.decide(1000.01), 1000.01, 0.0001)
    assert planner.decide(1000.5) == math.inf and stale == [driver], "stale and idle"
    follow.update(driver, 6, 1001.0)
    assert follow.next_due() == 1001.0
    slot = planner.decide(1001.0)
    assert slot.source is follow and slot.request.frame == ("follow", (("la1", 6),))
    run(planner, slot, 1001.0, 0.0001)
    stats = follow.counters.snapshot(1002.0)
    assert stats.follow_intervals == 1, "only the interval between the first two ticks"
    assert abs(stats.follow_error_p50_s) < 1e-9


def test_a_stream_begun_right_after_one_ended_waits_a_period_from_the_last_tick() -> None:
    """``end_follow`` just after a tick, a new stream at once: its first tick is a period
    after the last one, never sooner (no interval under the period, whatever the streams)."""
    follow = FollowTicker(Follower, 0.010, BusCounters(0.0), on_stale=lambda driver: None)
    driver = Follower("la1", 1)
    follow.update(driver, 5, 0.0)
    follow.build(0.0)
    follow.sent(0.0)
    follow.stop("la1")
    follow.update(driver, 6, 0.002)
    assert follow.next_due() == pytest.approx(0.010)


@pytest.mark.parametrize("ending", ["stopped", "reached"])
def test_a_stream_ended_then_another_is_a_pause_not_an_interval(ending) -> None:
    """An ``end_follow`` (``stop``) or a ramp's end, then a new stream seconds later: the
    ticker was idle, so the pause is no follow interval (it was counted as one, 5 s late)."""
    planner = BusPlanner(TIMING)
    follow = FollowTicker(Follower, 0.010, BusCounters(0.0), on_stale=lambda driver: None)
    planner.tickers.append(follow)
    driver = Follower("la1", 1)
    follow.update(driver, 5, 0.0, ends_on_target=ending == "reached")
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    if ending == "stopped":
        run(planner, planner.decide(0.010), 0.010, 0.0001)
        follow.stop("la1")
    assert follow.next_due() is None
    follow.update(driver, 6, 5.0)
    assert follow.next_due() == 5.0
    run(planner, planner.decide(5.0), 5.0, 0.0001)
    run(planner, planner.decide(5.010), 5.010, 0.0001)
    stats = follow.counters.snapshot(6.0)
    assert stats.follow_intervals == (2 if ending == "stopped" else 1)
    assert abs(stats.follow_error_p99_s) < 1e-6, "the pause counted as an interval"


# -- keep-alives -----------------------------------------------------------------------------


class Keeper(Follower):
    """Needs its keep-alive every 0.5 s while ``running``."""

    running = True

    def keepalive(self, now: float):
        return (0.5, silent(("keepalive", now))) if self.running else None


def test_a_keepalive_is_due_a_period_after_the_last_one_and_only_while_needed():
    driver = Keeper("z1", 1)
    keep = KeepaliveTicker(driver)
    assert keep.next_due() == 0.5
    assert keep.build(0.5).frame == ("keepalive", 0.5)
    keep.sent(0.75)
    assert keep.next_due() == 1.25 and keep.period_s == 0.5
    driver.running = False
    assert keep.next_due() is None and keep.build(1.25) is None


# -- follow streams --------------------------------------------------------------------------


def streams_of(*drivers: Driver) -> tuple[BusPlanner, FollowStreams]:
    planner = BusPlanner(TIMING)
    return planner, FollowStreams(planner, BusCounters(0.0), {d.name: d for d in drivers})


def test_streams_of_one_kind_and_period_share_a_ticker_up_to_its_limit():
    a, b, c = (Follower(f"la{i}", i, follow_period_s=0.010) for i in (1, 2, 3))
    slower = Follower("la4", 4, follow_period_s=0.020)
    other = OtherFollower("x1", 5, follow_period_s=0.010)
    planner, streams = streams_of(a, b, c, slower, other)
    planner.tickers.append(KeepaliveTicker(Keeper("z1", 9)))
    for driver in (a, b, c, slower, other):
        streams.start(driver, driver.name, 0.0)
    streams.start(a, "again", 0.0)  # a running stream is fed on its own ticker
    carried = sorted(sorted(t.streams) for t in planner.tickers if isinstance(t, FollowTicker))
    assert carried == [["la1", "la2"], ["la3"], ["la4"], ["x1"]]
    assert streams.following("la1") and not streams.following("z1")


def test_store_latest_feeds_a_running_stream_only():
    driver = Follower("la1", 1)
    planner, streams = streams_of(driver)
    assert not streams.store_latest("la1", 5, 0.0, "position"), (
        "no stream yet: the bus thread starts it"
    )
    streams.start(driver, 5, 0.0)
    assert not streams.store_latest("la1", 7, 0.001, "velocity"), "a speed is no position"
    assert streams.store_latest("la1", 6, 0.001, "position")
    assert planner.decide(0.001).request.frame == ("follow", (("la1", 6),))


def test_store_latest_never_feeds_a_ramp():
    """A ramp ends on its target and never goes stale: a follow target stored into it (a
    put of another thread) would be kept for ever. The bus thread makes it a stream."""
    driver = Follower("la1", 1)
    _, streams = streams_of(driver)
    streams.start(driver, 5, 0.0, ends_on_target=True)
    assert not streams.store_latest("la1", 6, 0.001, "position")
    assert streams.following("la1") and not streams.fed("la1")
    streams.start(driver, 6, 0.001)
    assert streams.fed("la1") and streams.store_latest("la1", 7, 0.002, "position")


def test_a_stream_ended_is_reported_and_followed_by_its_stop():
    a, b = Follower("la1", 1), Follower("la2", 2)
    planner, streams = streams_of(a, b)
    streams.start(a, 5, 0.0)
    streams.start(b, 5, 0.0)
    streams.end("la1", "client left")
    assert [(e.type, e.fields) for e in a.drain_events()] == [
        ("stream_stopped", {"reason": "client left"})
    ]
    assert b.drain_events() == []
    assert not streams.store_latest("la1", 6, 0.001, "position") and streams.store_latest(
        "la2", 6, 0.001, "position"
    )
    tick = planner.decide(0.001)
    assert tick.request.frame == ("follow", (("la2", 6),)), "la1 left the tick"
    run(planner, tick, 0.001, 0.0001)
    slot = planner.decide(0.003)
    assert slot.priority is Priority.COMMAND and slot.request.frame == ("stop", "la1")


def test_a_stream_gone_stale_is_reported_and_followed_by_its_stop():
    driver = Follower("la1", 1)
    planner, streams = streams_of(driver)
    streams.start(driver, 5, 0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    slot = planner.decide(0.5)
    assert [e.type for e in driver.drain_events()] == ["stream_stale"]
    assert slot.priority is Priority.COMMAND and slot.request.frame == ("stop", "la1")
    assert not streams.store_latest("la1", 6, 0.5, "position")


def test_a_stale_streams_stop_is_queued_behind_a_full_queue_of_commands():
    """A stale stream's 0 rpm went to a full queue (another client's flood) and was lost:
    the wheel kept its speed."""
    driver = Follower("la1", 1)
    planner, streams = streams_of(driver)
    streams.start(driver, 5, 0.0)
    run(planner, planner.decide(0.0), 0.0, 0.0001)
    for n in range(COMMAND_QUEUE):
        assert planner.push_command(Job("la2", deque([asking(2)]), client=f"client{n}"))
    planner.decide(0.5)  # the stream goes stale
    assert [e.type for e in driver.drain_events()] == ["stream_stale"]
    assert planner.drop_commands()[-1].requests[0].frame == ("stop", "la1")


def test_streams_ended_all_at_once_are_reported_only():
    a, b = Follower("la1", 1), Follower("la2", 2)
    planner, streams = streams_of(a, b)
    streams.start(a, 5, 0.0)
    streams.start(b, 5, 0.0)
    streams.end_all("estop")
    for driver in (a, b):
        assert [(e.type, e.fields) for e in driver.drain_events()] == [
            ("stream_stopped", {"reason": "estop"})
        ]
        assert not streams.store_latest(driver.name, 6, 0.0, "position")
    assert planner.decide(0.0) == math.inf, "no stop is queued, no tick is due"


def test_a_cancelled_command_is_taken_out_and_never_sent():
    planner = BusPlanner(TIMING)
    job = Job("la1", deque([asking()]))
    planner.push_command(job)
    planner.discard(job)
    assert planner.queued == 0 and planner.decide(0.0) == math.inf


def test_a_stream_starts_with_its_target_and_its_ticks_are_counted_on_the_bus():
    driver = Follower("la1", 1, follow_period_s=0.010)
    counters = BusCounters(0.0)
    planner = BusPlanner(TIMING)
    streams = FollowStreams(planner, counters, {"la1": driver})
    streams.start(driver, 5, 0.0)
    first = planner.decide(0.0)
    assert first.request.frame == ("follow", (("la1", 5),))
    run(planner, first, 0.0, 0.0001)
    run(planner, planner.decide(0.010), 0.010, 0.0001)
    assert counters.snapshot(1.0).follow_intervals == 1


def test_the_stop_after_a_stream_ended_is_a_command_for_its_device():
    driver = Follower("la1", 1)
    planner, streams = streams_of(driver)
    streams.start(driver, 5, 0.0)
    streams.end("la1", "client left")
    slot = planner.decide(0.0)
    assert slot.source.device == "la1" and slot.request.frame == ("stop", "la1")


# -- where a stream starts from, and its limits told (tickers rules 4 and 6) ------------------


class Reading(Follower):
    """A follower of a family's joint whose telemetry, asked at a moment, is what the test set
    for that moment (a moment not set is a test's mistake: ``KeyError``)."""

    def __init__(self, joint: Joint, readings: dict[float, dict]) -> None:
        super().__init__(joint.name, 1, joint=joint, follow_period_s=0.01)
        self.readings = readings

    def telemetry(self, now: float) -> dict:
        return dict(self.readings[now])


def la_joint(**limits) -> Joint:
    return Joint.of("la1", inspire_la.JOINT, JointTable(unit="m", scale=5e-6, **limits))


def wheel_joint(**limits) -> Joint:
    table = JointTable(unit="rad", scale=2 * math.pi / 10_000, type="velocity", **limits)
    return Joint.of("wheel", zlac706.JOINT, table)


def test_a_position_stream_starts_from_the_target_else_the_position_read_at_its_moment():
    assert commanded(Reading(la_joint(), {5.0: {"target": 1200, "position": 900}}), 5.0) == 1200
    assert commanded(Reading(la_joint(), {5.0: {"position": 900}}), 5.0) == 900
    assert commanded(Reading(la_joint(), {5.0: {"target": 0, "position": 900}}), 5.0) == 0


def test_a_speed_stream_starts_from_the_commanded_speed_else_standing_still():
    assert commanded(Reading(wheel_joint(), {5.0: {"target_speed_rpm": -300,
                                                   "speed_rpm": 10}}), 5.0) == -300  # fmt: skip
    assert commanded(Reading(wheel_joint(), {5.0: {"speed_rpm": 10}}), 5.0) == 0.0


def limited_events(driver: Driver) -> list[dict]:
    return [event.fields for event in driver.drain_events() if event.type == "limited"]


def test_a_target_held_at_a_position_limit_is_told_once_in_si_naming_joint_and_limit():
    driver = Reading(la_joint(offset=0.001, max=0.006), {0.0: {"target": 0}})
    stream = FollowStream(driver, (1500, 0.0), StreamLimiter(driver.joint, 0.01, 0))
    assert stream.next_target() == 1000  # 0.006 m
    assert stream.next_target() == 1000
    assert limited_events(driver) == [  # a position: the offset counts
        {"joint": "la1", "limit": "max", "value": pytest.approx(0.0085)}
    ]


def test_a_speed_held_at_its_max_velocity_is_told_in_rad_per_s():
    driver = Reading(wheel_joint(max_velocity=1.0), {0.0: {}})
    stream = FollowStream(driver, (600, 0.0), StreamLimiter(driver.joint, 0.01, 0.0))
    assert stream.next_target() < 600
    velocity = driver.joint.velocity_si(600)
    assert limited_events(driver) == [
        {"joint": "wheel", "limit": "max_velocity", "value": pytest.approx(velocity)}
    ]


def test_a_ramp_steps_from_where_its_device_was_commanded_never_goes_stale_and_ends_on_it():
    """Rule 5: 10 mm/s at 10 ms is 20 counts a tick, from the target read when it started;
    ticks half a second later still carry it; the tick that sends the target ends it."""
    driver = Reading(la_joint(max_velocity=0.01), {0.0: {"target": 900, "position": 0}})
    planner, streams = streams_of(driver)
    streams.start(driver, 1000, 0.0, ends_on_target=True)
    sent = []
    for tick in range(5):
        moment = 0.5 + tick * 0.01
        slot = planner.decide(moment)
        sent.append(slot.request.frame[1][0][1])
        assert slot.source.carried() == [driver]
        run(planner, slot, moment, 0.0001)
    assert sent == [920, 940, 960, 980, 1000]
    assert planner.decide(0.55) == math.inf  # ended: nothing more to tick
    assert not streams.store_latest("la1", 1000, 0.55, "position")
    # held by max_velocity, told once; ended on its target, with no stale or stopped stream
    assert [event.type for event in driver.drain_events()] == ["limited"]


def test_ramps_one_after_another_beyond_a_limit_tell_it_once_until_one_ends_within_it():
    """A ROS controller sends its command each period: each command beyond a limit was a ramp
    of its own that ended on the limit and told it again (50 events a second a joint)."""
    driver = Reading(la_joint(max=0.005), {t / 100: {"target": 1000} for t in range(200)})
    planner, streams = streams_of(driver)

    def ramp(target: int, moment: float) -> list[str]:
        streams.start(driver, target, moment, ends_on_target=True)
        slot = planner.decide(moment)
        run(planner, slot, moment, 0.0001)
        assert planner.decide(moment + 0.01) == math.inf  # one tick: it ended on its goal
        return [event.type for event in driver.drain_events()]

    assert ramp(1500, 0.0) == ["limited"]  # 0.0075 m: held at 0.005
    assert ramp(1600, 0.1) == [] and ramp(1500, 0.2) == []  # still on it: said already
    assert ramp(1000, 0.3) == []  # on the limit itself: not held back, and not told
    assert ramp(1500, 0.4) == ["limited"]  # beyond it again after a ramp within it


def test_a_new_target_for_a_running_stream_steps_on_from_its_last_tick_not_from_telemetry():
    """A ramp handed to a device already streaming (a ROS command after a stream) keeps the
    stream's limiter: the next step starts where the last tick left the device, whatever its
    last reading (900, a poll behind) says."""
    readings = {0.0: {"target": 900}, 0.025: {"target": 900}}
    driver = Reading(la_joint(max_velocity=0.01), readings)
    planner, streams = streams_of(driver)
    streams.start(driver, 1000, 0.0)
    for moment in (0.0, 0.01):
        run(planner, planner.decide(moment), moment, 0.0001)  # 920, 940
    streams.start(driver, 1100, 0.025, ends_on_target=True)
    assert planner.decide(0.025).request.frame[1] == (("la1", 960),)
