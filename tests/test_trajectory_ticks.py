"""The ticks of a trajectory on a fake clock (gateway/scheduler/trajectory_ticks.py and
plays.py): the grid's slots (``next_slot``); a ticker samples the path at its slot's time
however late its frame is built, stays on the grid when a tick is late without ever starting
one less than a period after a late one, and keeps what it commanded; ``Plays`` moves devices
between tickers and out of them (holding, or a speed ramped to 0 over ``RAMP_S`` and then the
stale-stream stop). Times are plain floats and nothing sleeps; the frames are the drivers'
own, read back from their codec frames."""

from __future__ import annotations

import math
from itertools import pairwise

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs import inspire_la as la
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.inspire_la import InspireLaDriver, PowerStage
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.scheduler.planner import BusPlanner, Job, Priority, Slot
from busgate.gateway.scheduler.plays import END_ALL, RAMP_S, Plays
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.tickers import FollowTicker
from busgate.gateway.scheduler.trajectory_ticks import (
    GRID_STRETCH,
    LONGEST_INTERVAL_S,
    ON_TIME_S,
    TrajectoryTicker,
    grid_of,
    next_slot,
)
from busgate.gateway.trajectory.interpolation import Knot, Path, sent
from tests.test_driver_zlac706 import can_driver, plan, velocity_driver, wire
from tests.test_driver_zlac706 import run as applied
from tests.test_mutants_scheduler import la_joint, wheel_joint
from tests.test_planner import run as carried_out

PERIOD = 0.02
GRID = PERIOD * GRID_STRETCH  # the slots' spacing (rule 1 of trajectory_ticks.py)
START = 1000.0  # bus clock: a perf_counter far from 0, as on a host that has been up a while
TIMING = link_timing("inspire_la", 921_600, margin_s=0.0, gap_s=0.001)
#: A linear path from 0 to 1000 in one second: every slot's value differs from its neighbours'.
RAMP_UP = Path(0.0, [Knot(1.0, 1000.0)], "linear")


def position_of(path: Path):
    """The sampler the API gives a position device: the path at ``t_s``, rounded to send."""
    return lambda t_s: {"position": sent(path.at(t_s))}


def positions(slot_or_request) -> dict[int, int]:
    """Each actuator's position in an LA follow frame (``0x19`` or ``0xF3``), by id."""
    request = getattr(slot_or_request, "request", slot_or_request)
    frame = request.frame
    if isinstance(frame, la.GroupFollowCommand):
        return {target.device_id: target.position_raw for target in frame.targets}
    assert isinstance(frame, la.FollowCommand) and not frame.reply
    return {frame.device_id: frame.position_raw}


def la_ticker(*drivers: InspireLaDriver, path: Path = RAMP_UP) -> TrajectoryTicker:
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, START, BusCounters(0.0))
    for driver in drivers or (InspireLaDriver("la1", 1),):
        ticker.add(driver, position_of(path))
    return ticker


def slot_value(k: int, path: Path = RAMP_UP) -> int:
    return sent(path.at(k * GRID))


# --- next_slot ------------------------------------------------------------------------------


@pytest.mark.parametrize(("earliest", "expected_k"), [
    (START - 5.0, 0),  # before the start: the start itself
    (START, 0),
    (START + 0.02, 1),  # on a slot: that slot
    (START + 0.0200001, 2),  # just past one: the next
    (START + 0.039, 2),
    (START + 0.02 * 999, 999),
])
def test_next_slot_is_the_first_slot_at_or_after_the_earliest_moment(earliest, expected_k):
    assert next_slot(START, PERIOD, earliest) == pytest.approx(START + expected_k * PERIOD,
                                                               abs=1e-12)


@given(start=st.floats(0.0, 1e6), period=st.floats(0.01, 0.05), ahead=st.floats(-10.0, 3600.0))
def test_next_slot_is_on_the_grid_not_before_the_earliest_and_no_slot_is_passed(
        start, period, ahead):
    earliest = start + ahead
    slot = next_slot(start, period, earliest)
    k = (slot - start) / period
    assert k >= 0 and k == pytest.approx(round(k), abs=1e-6)  # a slot of the grid
    resolution = 1e-9 * period + 4 * math.ulp(start + 3600.0)  # the rounding of floats
    assert slot >= earliest - resolution  # never before the earliest moment (an interval)
    assert slot == start or slot - period < earliest + resolution  # and the first such slot


# --- TrajectoryTicker ------------------------------------------------------------------------


def test_a_tick_built_late_sends_the_path_at_its_slot_not_at_the_moment_of_building():
    ticker = la_ticker()
    assert ticker.next_due() == START
    assert positions(ticker.build(START + 0.015)) == {1: slot_value(0)}
    ticker.sent(START + 0.016)  # 16 ms late: the next slot is a full period after that
    assert ticker.commanded["la1"] == (0.0, slot_value(0))
    assert ticker.next_due() == pytest.approx(START + 2 * GRID)
    assert positions(ticker.build(START + 0.05)) == {1: slot_value(2)} == {1: 40}
    ticker.sent(START + 0.05)
    t_s, value = ticker.commanded["la1"]
    assert (t_s, value) == (pytest.approx(2 * GRID), 40)


def test_a_slot_is_sampled_at_k_periods_exactly_whatever_the_bus_clock_reads():
    """At 1000.0 s of bus clock, slot 2's bus time less the start is 0.0403999999999769 s:
    a path at 0.5 (a half: sent as 1) there would be sent as 0."""
    half_way = Path(0.0, [Knot(4 * GRID, 1.0)], "linear")
    assert (START + 2 * GRID) - START < 2 * GRID and sent(half_way.at(2 * GRID)) == 1
    ticker = la_ticker(path=half_way)
    for k in range(3):
        assert positions(ticker.build(ticker.next_due())) == {1: [0, 0, 1][k]}
        ticker.sent(ticker.next_due())
    assert ticker.commanded["la1"] == (2 * GRID, 1)


def test_commanded_is_what_was_sent_not_a_tick_built_ahead_and_put_off():
    """The bus thread builds a tick ahead of its slot and may put it off (new work came):
    until it is sent, the feedback and the verdict see the tick before it."""
    ticker = la_ticker()
    ticker.build(START)
    ticker.sent(START)
    ticker.build(START + GRID - 0.003)  # prepared 3 ms ahead, then put off
    assert ticker.commanded["la1"] == (0.0, 0)
    ticker.build(START + GRID)
    ticker.sent(START + GRID)
    assert ticker.commanded["la1"] == (pytest.approx(GRID), 20)


def test_a_tick_a_little_after_its_slot_is_on_time_and_every_slot_is_sent():
    """A write starts a little after its slot (50 µs here, the host's write): the next tick is
    the next slot, so the wire carries the path at every slot, not at every other one."""
    ticker = la_ticker()
    sent_values = []
    for _ in range(10):
        due = ticker.next_due()
        sent_values.append(positions(ticker.build(due))[1])
        ticker.sent(due + 0.00005)
    assert sent_values == [slot_value(k) for k in range(10)]


lateness = st.one_of(st.floats(0.0, ON_TIME_S), st.floats(ON_TIME_S, 3 * PERIOD))


@given(st.lists(lateness, min_size=2, max_size=60))
def test_ticks_stay_on_the_grid_and_no_interval_is_shorter_than_the_period(latenesses):
    """Each tick starts ``lateness`` after it is due: every one is built at a slot with the
    path's value there and is due at its slot or a full period after the tick before,
    whichever is later, so no interval is ever shorter than the period; after a tick within
    ``ON_TIME_S`` of its slot comes the next slot, after a later one the first slot a full
    period on. (The rule before allowed an interval ``ON_TIME_S`` short.)"""
    ticker = la_ticker()
    previous = None  # (slot index, start) of the tick before
    for late in latenesses:
        due = ticker.next_due()
        k = math.floor((due - START) / GRID + 1e-9)  # due at its slot, or held back after it
        slot = START + k * GRID
        start = due + late
        assert positions(ticker.build(start)) == {1: slot_value(k)}
        if previous is None:
            assert (k, due) == (0, START)
        else:
            last_k, last_start = previous
            assert due == max(slot, last_start + PERIOD)  # never a short interval
            if last_start - (START + last_k * GRID) <= ON_TIME_S:
                assert k == last_k + 1
            else:  # drifted: the first slot a period on, and none passed needlessly
                assert slot >= last_start + PERIOD - 1e-9 > slot - GRID
        ticker.sent(start)
        previous = (k, start)


@pytest.mark.parametrize("period_s", [0.026, 0.03, 0.045])
def test_after_a_late_tick_a_long_period_takes_the_next_slot_never_leaving_over_50_ms(period_s):
    """The manual takes follow targets at most 50 ms apart: where the first slot a full period
    after a late tick would be further than that (a period over 25 ms skips one), the next
    tick is the next slot, a period after the late one, and the stretch brings the ticks back
    onto their slots."""
    grid = grid_of(period_s)
    ticker = TrajectoryTicker(InspireLaDriver, period_s, START, BusCounters(0.0))
    ticker.add(InspireLaDriver("la1", 1), position_of(RAMP_UP))
    starts, slots = [], []
    for index in range(40):
        due = ticker.next_due()
        slots.append(math.floor((due - START) / grid + 1e-9))
        start = due + (0.002 if index == 3 else 0.00005)  # one tick 2 ms late
        assert positions(ticker.build(start)) == {1: sent(RAMP_UP.at(slots[-1] * grid))}
        ticker.sent(start)
        starts.append(start)
    assert slots == list(range(40)), "no slot is skipped"
    intervals = [b - a for a, b in pairwise(starts)]
    assert min(intervals) >= period_s and max(intervals) <= LONGEST_INTERVAL_S + 0.002
    assert intervals[3] == pytest.approx(period_s + 0.00005)
    assert starts[-1] - (START + 39 * grid) < ON_TIME_S, "back on its slot"


def test_a_50_ms_grid_is_not_stretched_past_the_manuals_longest_interval():
    assert grid_of(0.05) == 0.05 and grid_of(0.0499) == pytest.approx(0.05)
    assert grid_of(0.02) == pytest.approx(0.0202) and grid_of(0.01) == pytest.approx(0.0101)
    ticker = TrajectoryTicker(InspireLaDriver, 0.05, START, BusCounters(0.0))
    ticker.add(InspireLaDriver("la1", 1), position_of(RAMP_UP))
    starts = []
    for _ in range(20):
        start = ticker.next_due() + 0.00005  # each write a little late: carried, not skipped
        ticker.build(start)
        ticker.sent(start)
        starts.append(start)
    assert all(b - a == pytest.approx(0.05 + 0.00005) for a, b in pairwise(starts))


def test_a_late_tick_at_20_ms_still_gives_up_the_next_slot():
    ticker = la_ticker()
    ticker.build(START)
    ticker.sent(START + 0.002)
    assert ticker.next_due() == pytest.approx(START + 2 * GRID)  # 38.4 ms on: within 50


def test_ticks_each_a_little_late_keep_every_slot_and_every_interval_at_the_period():
    """A host whose writes start 60 µs after they are due, and a tick 0.9 ms late every so
    often: the stretched grid gives the lateness back, so no slot is left out, the next tick
    is on its slot again, and no interval is under the period (on the rule before, the tick
    after the late one made an interval of 19.16 ms)."""
    ticker = la_ticker()
    starts, slots = [], []
    for index in range(200):
        due = ticker.next_due()
        slots.append(math.floor((due - START) / GRID + 1e-9))
        start = due + (0.0009 if index % 7 == 0 else 0.00006)
        ticker.build(start)
        ticker.sent(start)
        starts.append(start)
    assert slots == list(range(200))
    assert min(b - a for a, b in pairwise(starts)) >= PERIOD
    assert max(s - (START + k * GRID) for s, k in zip(starts, slots, strict=True)) < 0.0011


def test_each_interval_is_counted_against_the_period():
    counters = BusCounters(0.0)
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, START, counters)
    ticker.add(InspireLaDriver("la1", 1), position_of(RAMP_UP))
    for start in (START + 0.0001, START + 0.0202, START + 0.0601):  # the second one late
        ticker.build(start)
        ticker.sent(start)
    stats = counters.snapshot(START + 1)
    assert stats.follow_intervals == 2
    assert stats.follow_error_min_s == pytest.approx(0.0201 - PERIOD)
    assert stats.follow_error_p99_s == pytest.approx(0.0399 - PERIOD)


def test_the_devices_of_a_ticker_share_one_frame_each_with_its_own_path():
    other = Path(2000.0, [Knot(0.5, 0.0)], "linear")
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, START, BusCounters(0.0))
    ticker.add(la1, position_of(RAMP_UP))
    ticker.add(la2, position_of(other))
    ticker.build(START)
    ticker.sent(START)
    request = ticker.build(START + GRID)
    assert isinstance(request.frame, la.GroupFollowCommand) and request.expected is None
    assert positions(request) == {1: 20, 2: sent(other.at(GRID))} == {1: 20, 2: 1919}
    assert ticker.carried() == [la1, la2]
    ticker.sent(START + GRID)
    assert ticker.commanded == {"la1": (pytest.approx(GRID), 20),
                                "la2": (pytest.approx(GRID), 1919)}
    ticker.remove("la1")
    ticker.remove("la2")
    assert ticker.next_due() is None and ticker.build(START + 1) is None


def test_a_device_that_cannot_take_its_target_is_left_out_and_no_tick_raises():
    """An e-stopped actuator, a ZLAC706 out of velocity mode: each is left out with its
    reason and its neighbours' frame goes on; with no device left the slot passes without a
    frame and the next one is due (the bus thread takes an exception for a bug)."""
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    ticker = la_ticker(la1, la2)
    la1.safe_stop()  # its e-stop
    assert positions(ticker.build(START)) == {2: 0}
    assert ticker.carried() == [la2] and set(ticker.refused) == {"la1"}
    assert "e-stopped" in ticker.refused["la1"]
    ticker.sent(START)
    la2.safe_stop()
    assert ticker.build(START + GRID) is None
    assert ticker.next_due() is None  # nobody left to tick for
    wheel = can_driver()  # no mode yet: a speed target is refused
    ticker = TrajectoryTicker(Zlac706CanDriver, PERIOD, START, BusCounters(0.0))
    ticker.add(wheel, lambda t_s: {"rpm": 100.0})
    ticker.add(InspireLaDriver("la3", 3), position_of(RAMP_UP))  # stays: it can take its own
    ticker.remove("la3")
    assert ticker.build(START + 0.0005) is None
    assert "velocity mode" in ticker.refused["wheel"]


def test_a_slot_without_a_frame_passes_and_the_next_is_after_now():
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    passed = []
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, START, BusCounters(0.0), passed.append)
    ticker.add(la1, position_of(RAMP_UP))
    la1.safe_stop()
    ticker.add(la2, position_of(RAMP_UP))
    la2.safe_stop()
    assert ticker.build(START + 0.05) is None and passed == [ticker]
    ticker.add(la2, position_of(RAMP_UP))  # were it still playing, the next slot is after now
    assert ticker.next_due() == pytest.approx(START + 0.06)


def test_a_ticker_has_room_for_its_kinds_group_limit():
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, START, BusCounters(0.0))
    limit = InspireLaDriver.follow_group_limit
    drivers = [InspireLaDriver(f"la{i}", i) for i in range(1, limit + 2)]
    for driver in drivers[:-1]:
        assert ticker.has_room(driver)
        ticker.add(driver, position_of(RAMP_UP))
    assert not ticker.has_room(drivers[-1]) and ticker.has_room(drivers[0])


# --- Plays -----------------------------------------------------------------------------------


def bus_of(*drivers) -> tuple[BusPlanner, Plays, FollowStreams]:
    planner = BusPlanner(TIMING)
    counters = BusCounters(0.0)
    by_name = {driver.name: driver for driver in drivers}
    streams = FollowStreams(planner, counters, by_name)
    return planner, Plays(planner, counters, by_name, streams), streams


def trajectory_tickers(planner: BusPlanner) -> list[TrajectoryTicker]:
    return [t for t in planner.tickers if isinstance(t, TrajectoryTicker)]


def tick(planner: BusPlanner, now: float) -> Slot:
    """The follow tick due at ``now``, carried out (its frame takes 0.2 ms)."""
    slot = planner.decide(now)
    assert isinstance(slot, Slot) and slot.priority is Priority.FOLLOW, slot
    carried_out(planner, slot, now, 0.0002)
    return slot


def three_actuators() -> list[InspireLaDriver]:
    return [InspireLaDriver(f"la{i}", i) for i in (1, 2, 3)]


def test_devices_started_together_share_one_ticker_and_one_frame():
    planner, plays, _ = bus_of(*three_actuators())
    plays.start({f"la{i}": position_of(RAMP_UP) for i in (1, 2, 3)}, START)
    assert len(trajectory_tickers(planner)) == 1
    assert planner.decide(START - 0.01) == START  # nothing before the start
    assert positions(tick(planner, START)) == {1: 0, 2: 0, 3: 0}
    assert positions(tick(planner, START + GRID)) == {1: 20, 2: 20, 3: 20}
    assert plays.commanded("la2") == (pytest.approx(GRID), 20)
    assert plays.commanded("la9") is None


def test_a_new_start_takes_a_device_from_its_old_ticker_from_the_next_tick():
    planner, plays, _ = bus_of(*three_actuators())
    plays.start({"la1": position_of(RAMP_UP), "la2": position_of(RAMP_UP)}, START)
    tick(planner, START)
    later = START + 5 * PERIOD + 0.003  # another grid
    down = Path(500.0, [Knot(1.0, 0.0)], "linear")
    plays.start({"la2": position_of(down)}, later)
    assert positions(tick(planner, START + GRID)) == {1: 20}  # la2 has left the old ticker
    assert plays.commanded("la2") is None  # until its new trajectory's first tick
    for k in range(2, 6):
        assert positions(tick(planner, START + k * GRID)) == {1: slot_value(k)}
    assert positions(tick(planner, later)) == {2: 500}
    plays.start({"la1": position_of(down)}, later)  # its old ticker is left empty: dropped
    assert len(trajectory_tickers(planner)) == 1
    assert positions(tick(planner, later + GRID)) == {1: 490, 2: 490}


def test_a_trajectory_takes_a_device_from_its_follow_stream_without_stopping_it():
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    planner, plays, streams = bus_of(la1, la2)
    streams.start(la1, 700, START - 1.0)
    streams.start(la2, 800, START - 1.0)
    la1.drain_events()
    plays.start({"la1": position_of(RAMP_UP)}, START)
    [follow] = [t for t in planner.tickers if isinstance(t, FollowTicker)]
    assert list(follow.streams) == ["la2"]  # la1 left its stream for the trajectory
    assert [(e.type, e.fields) for e in la1.drain_events()] == [
        ("stream_stopped", {"reason": "trajectory"})]
    assert planner.queued == 0  # no stale-stream requests: the trajectory goes on from there
    assert not streams.store_latest("la1", 900, START, "position")  # the stream is gone for good


def sent_tick(planner: BusPlanner, now: float) -> Slot:
    """The follow tick due at ``now``, carried out in ``Execution``'s order: each driver it
    carried told its frame went (no reply), its ticker, the spacing, the line."""
    slot = planner.decide(now)
    assert isinstance(slot, Slot) and slot.priority is Priority.FOLLOW, slot
    for driver in slot.source.carried():
        driver.apply(slot.request, (), now + 0.0002)
    slot.source.sent(now)
    planner.spacing.ticked(slot.source.carried(), slot.source, now)
    planner.finished(slot, now + 0.0002, failed=False)
    return slot


def test_an_actuator_whose_stream_ended_is_held_where_its_last_tick_sent_it():
    """An LA's follow frame has no reply: its state says the last tick's target only at the
    next poll, so a play checked before then starts from that tick (``plays`` rule 4), not
    from the older target its state says (an audit: a play's first tick jumped 1560→1160)."""
    la1, la2, la3 = three_actuators()
    planner, plays, streams = bus_of(la1, la2, la3)
    streams.start(la1, 1560, START)
    streams.start(la2, 700, START, ends_on_target=True)  # a ramp: it ends with its target
    assert positions(sent_tick(planner, START)) == {1: 1560, 2: 700}
    assert plays.held("la2") == (START, 700), "a ramp's end is held once its tick went"
    assert plays.held("la1") is None, "streaming still"
    streams.start(la3, 300, START + PERIOD)
    streams.end("la1", "its client left")
    assert plays.held("la1") == (START, 1560)
    assert positions(sent_tick(planner, START + PERIOD)) == {3: 300}
    assert plays.held("la3") is None
    streams.end_all("estop")
    assert plays.held("la3") == (START + PERIOD, 300)


#: 0.01 m/s on a 5 µm count: 2000 counts/s, 40 counts in one follow period (``PERIOD``).
LIMITED = {"max_velocity": 0.01}


def test_a_play_reaching_the_bus_a_step_past_the_limit_from_a_running_stream_does_not_start():
    """``plays`` rule 6: a play is checked from where the device was commanded when it was
    accepted (an LA's state says a stream's target only at a poll); its stream goes on
    until the play reaches the bus. A first tick past max_velocity in one period from where
    the stream sent it last is refused there (a tick gone between the check and the bus made
    it twice the limit: a review), and the stream goes on, untaken. A device whose first tick
    is within goes, from there."""
    la1 = InspireLaDriver("la1", 1, joint=la_joint(**LIMITED))
    la2 = InspireLaDriver("la2", 2, joint=la_joint(**LIMITED))
    planner, plays, streams = bus_of(la1, la2)
    for driver in (la1, la2):
        streams.start(driver, 0, START)  # its first target: where it is, nothing being known
    positions(sent_tick(planner, START))
    for driver in (la1, la2):
        streams.start(driver, 2000, START)
    sent = [positions(sent_tick(planner, START + k * PERIOD)) for k in range(1, 5)]
    assert [s[1] - before[1] for before, s in pairwise(sent)] == [40, 40, 40]  # limited
    last = sent[-1]
    start = START + 6 * PERIOD
    jump = Path(float(last[1] - 41), [Knot(1.0, 0.0)], "linear")  # checked a tick back
    near = Path(float(last[2] - 40), [Knot(1.0, 0.0)], "linear")
    plays.start({"la1": position_of(jump), "la2": position_of(near)}, start)
    assert plays.refusal("la1") == (start, (
        "would step -0.000205 m at its first tick from where its follow stream had sent it when "
        "the play reached its bus, past its max_velocity in one follow period"))
    assert not plays.playing("la1") and streams.following("la1")  # it streams on
    assert plays.refusal("la2") is None and plays.playing("la2")
    assert not streams.following("la2")
    assert positions(tick(planner, start)) == {2: last[2] - 40}
    assert "stream_stopped" not in [e.type for e in la1.drain_events()]


def test_a_play_reaching_the_bus_a_step_past_the_limit_from_a_running_trajectory_holds_it():
    """``plays`` rule 6, a trajectory taken over: the old one ticked on after the new one was
    checked from an earlier tick. Past max_velocity in one period from its last tick, the
    device holds there (rule 3) and the new one is refused; within, it goes on from there."""
    la1 = InspireLaDriver("la1", 1, joint=la_joint(**LIMITED))
    planner, plays, _ = bus_of(la1)
    plays.start({"la1": position_of(RAMP_UP)}, START)  # 20 counts a tick
    for k in range(6):
        tick(planner, START + k * GRID)
    later = START + 10 * GRID
    checked_at = slot_value(3)  # two ticks back: 61 → 101 is 40 counts, then 101 → 60
    plays.start({"la1": position_of(Path(float(checked_at - 1), [Knot(1.0, 0.0)], "linear"))},
                later)
    assert plays.refusal("la1")[1].startswith("would step -0.000205 m at its first tick from "
                                              "where its trajectory had sent it")
    assert plays.held("la1")[1] == slot_value(5) and trajectory_tickers(planner) == []
    assert planner.decide(later) == math.inf  # it holds: nothing more goes
    plays.start({"la1": position_of(Path(float(slot_value(5) - 40), [Knot(1.0, 0.0)], "linear"))},
                later)
    assert plays.refusal("la1") is None  # within one period's step: it goes
    assert positions(tick(planner, later)) == {1: slot_value(5) - 40}


def test_a_speed_play_reaching_the_bus_a_step_past_max_acceleration_ramps_the_old_one_down():
    """``plays`` rule 6 for a speed: from the old trajectory's 300 rpm, a first tick of 0 rpm
    is past max_acceleration in one period: the new play is refused and the wheel ramps to 0
    over ``RAMP_S`` as a stopped speed does (rule 3), never left turning."""
    wheel = velocity_driver(Zlac706CanDriver("wheel", 1, joint=wheel_joint(max_acceleration=10.0)),
                            rpm=0)
    applied(wheel, plan(wheel, '{"op":"enable"}'))
    applied(wheel, plan(wheel, '{"op":"velocity","rpm":300}'))  # where the old one starts
    planner, plays, _ = bus_of(wheel)
    plays.start({"wheel": lambda t_s: {"rpm": 300.0}}, START)
    for k in range(3):
        tick(planner, START + k * GRID)
    plays.start({"wheel": lambda t_s: {"rpm": 0.0}}, START + 5 * GRID)
    assert "past its max_acceleration" in plays.refusal("wheel")[1]
    [ticker] = trajectory_tickers(planner)
    tick(planner, START + 3 * GRID)
    assert 0 < ticker.commanded["wheel"][1] < 300.0  # ramping down on the old one's grid


def test_a_position_device_stopped_holds_its_last_target():
    planner, plays, _ = bus_of(*three_actuators())
    plays.start({"la1": position_of(RAMP_UP), "la2": position_of(RAMP_UP)}, START)
    for k in range(3):
        tick(planner, START + k * GRID)
    plays.stop("la1", speed=False)
    assert positions(tick(planner, START + 3 * GRID)) == {2: slot_value(3)}
    assert plays.commanded("la1") is None
    plays.stop("la2", speed=False)
    assert trajectory_tickers(planner) == [] and planner.queued == 0
    assert planner.decide(START + 4 * GRID) == math.inf  # nothing more to send


def test_a_speed_stopped_ramps_to_zero_over_ramp_s_then_gets_the_stale_stream_stop():
    wheel = velocity_driver(can_driver(), rpm=0)
    planner, plays, _ = bus_of(wheel)
    plays.start({"wheel": lambda t_s: {"rpm": 300.0}}, START)
    for k in range(6):
        tick(planner, START + k * GRID)
    plays.stop("wheel", speed=True)
    [ticker] = trajectory_tickers(planner)
    ramp_ticks = math.ceil(RAMP_S / GRID)  # the last one at or past the ramp's end: 0 rpm
    sent_rpms = []
    for k in range(6, 6 + ramp_ticks):
        request = tick(planner, START + k * GRID).request
        t_s, rpm = ticker.commanded["wheel"]
        expected = 300.0 * max(0.0, 1 - (t_s - 5 * GRID) / RAMP_S)
        assert rpm == pytest.approx(expected, abs=1e-9)
        assert wire([request]) == wire([Zlac706CanDriver.follow_request(
            [(wheel, wheel.follow_target({"rpm": rpm}))])])
        sent_rpms.append(rpm)
    assert sent_rpms == sorted(sent_rpms, reverse=True) and sent_rpms[-1] == pytest.approx(0)
    assert trajectory_tickers(planner) == [] and plays.commanded("wheel") is None
    stop = planner.decide(START + (6 + ramp_ticks) * GRID)
    assert isinstance(stop, Slot) and isinstance(stop.source, Job)
    assert wire(list(stop.source.requests)) == wire(wheel.stale_stream())  # 0 rpm


def test_a_speed_that_never_ticked_leaves_at_once():
    wheel = velocity_driver(can_driver(), rpm=0)
    planner, plays, _ = bus_of(wheel)
    plays.start({"wheel": lambda t_s: {"rpm": 300.0}}, START)
    plays.stop("wheel", speed=True)
    assert trajectory_tickers(planner) == [] and planner.queued == 0


def test_a_device_left_out_leaves_its_trajectory_with_the_reason_until_it_plays_again():
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    planner, plays, _ = bus_of(la1, la2)
    plays.start({"la1": position_of(RAMP_UP), "la2": position_of(RAMP_UP)}, START)
    tick(planner, START)
    la1.safe_stop()
    assert positions(tick(planner, START + GRID)) == {2: 20}
    assert plays.commanded("la1") is None
    start, reason = plays.refusal("la1")
    assert start == START and reason.startswith("could not take its target") and (
        "e-stopped" in reason)
    assert plays.refusal("la2") is None
    la2.safe_stop()
    assert planner.decide(START + 2 * GRID) == math.inf  # the slot passed, the ticker went
    assert trajectory_tickers(planner) == [] and plays.refusal("la2")[0] == START
    la1.power = PowerStage.ON  # enabled again
    plays.start({"la1": position_of(RAMP_UP)}, START + 1.0)
    assert plays.refusal("la1") is None


def test_a_device_that_left_is_held_where_its_last_tick_sent_it():
    planner, plays, _ = bus_of(*three_actuators())
    plays.start({"la1": position_of(RAMP_UP), "la2": position_of(RAMP_UP)}, START)
    for k in range(3):
        tick(planner, START + k * GRID)
    assert plays.held("la1") is None  # playing: commanded says where it is
    plays.stop("la1", speed=False)
    assert plays.held("la1") == (START + 2 * GRID, 40)
    plays.start({"la2": position_of(RAMP_UP)}, START + 1.0)  # taken by another: held too
    assert plays.held("la2") == (START + 2 * GRID, 40)
    assert plays.held("la3") is None


def test_end_all_takes_every_device_out_at_once_saying_so():
    wheel = velocity_driver(can_driver(), rpm=0)
    planner, plays, _ = bus_of(*three_actuators(), wheel)
    plays.start({"la1": position_of(RAMP_UP), "wheel": lambda t_s: {"rpm": 300.0}}, START)
    plays.start({"la2": position_of(RAMP_UP)}, START + 0.005)
    tick(planner, START)
    tick(planner, START + 0.002)  # the wheel's ticker: one device a frame
    plays.stop("wheel", speed=True)  # ramping: out at once all the same
    plays.end_all("the bus lost")
    lost = END_ALL.format(why="the bus lost")
    assert trajectory_tickers(planner) == [] and planner.queued == 0
    assert all(plays.commanded(name) is None for name in ("la1", "la2", "wheel"))
    assert plays.refusal("la1") == plays.refusal("wheel") == (START, lost)
    assert plays.refusal("la2") == (START + 0.005, lost)  # the start of its own trajectory
    assert plays.refusal("la3") is None  # it played nothing
