"""A device's follow targets keep its follow period when it passes from one sender to another
(``spacing``): a command's follow, a stream's ticker, a trajectory's. Fake clock: times are
plain floats (the bus clock), nothing sleeps."""

from __future__ import annotations

import math
from collections import deque
from concurrent.futures import Future

from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.scheduler.planner import BusPlanner, Job
from busgate.gateway.scheduler.spacing import FollowSpacing
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.tickers import FollowTicker
from busgate.gateway.scheduler.trajectory_ticks import TrajectoryTicker
from tests.test_planner import TIMING, FollowingDriver, silent_request

PERIOD = 0.010


def command_follow(spacing: FollowSpacing, *devices: str) -> Job:
    """A command's job carrying ``devices`` follow-mode targets, planned, not yet sent."""
    job = Job(devices[0], deque([silent_request()]), future=Future())
    spacing.commanded(devices, job)
    return job


def sent(spacing: FollowSpacing, job: Job, at: float) -> None:
    """``job``'s frame went at ``at`` (as ``Execution`` and the planner see it)."""
    job.requests.popleft()
    spacing.job_sent(job, at)


def stream_ticker(spacing: FollowSpacing) -> FollowTicker:
    return FollowTicker(
        FollowingDriver, PERIOD, BusCounters(0.0), on_stale=lambda d: None, spacing=spacing
    )


def carried(ticker) -> list[str]:
    return [driver.name for driver in ticker.carried()]


def test_the_last_follow_target_from_any_sender_and_when_the_next_from_another_is_due():
    spacing, ticker = FollowSpacing(), object()
    assert spacing.last("la1") == -math.inf and spacing.due("la1", PERIOD, ticker) == -math.inf
    job = command_follow(spacing, "la1", "la2")
    assert spacing.last("la1") is None, "its command waits: when it goes is not known"
    assert spacing.due("la2", PERIOD, ticker) == math.inf
    assert spacing.due("la1", PERIOD, job) == -math.inf, "the command itself is not held"
    sent(spacing, job, 5.0)
    assert spacing.last("la1") == spacing.last("la2") == 5.0
    assert spacing.due("la1", PERIOD, ticker) == 5.0 + PERIOD
    spacing.ticked([FollowingDriver("la1", 1)], ticker, 5.02)
    assert spacing.last("la1") == 5.02 and spacing.last("la2") == 5.0
    assert spacing.due("la1", PERIOD, ticker) == -math.inf, "a ticker keeps its own period"
    assert spacing.due("la1", PERIOD, object()) == 5.02 + PERIOD


def test_a_command_taken_out_unsent_holds_nothing_back():
    spacing = FollowSpacing()
    job = command_follow(spacing, "la1")
    job.future.set_exception(RuntimeError("expired"))  # answered without it: it never goes
    assert spacing.last("la1") == -math.inf
    assert spacing.due("la1", PERIOD, object()) == -math.inf


def test_a_stream_started_right_after_a_command_follow_ticks_a_period_after_it():
    spacing = FollowSpacing()
    job = command_follow(spacing, "la1")
    ticker = stream_ticker(spacing)
    ticker.update(FollowingDriver("la1", 1), 900, 1.0)
    assert ticker.build(1.0) is None, "the command still waits to go out"
    assert ticker.next_due() == 1.0 + PERIOD, "looked at again a period on"
    sent(spacing, job, 1.004)
    assert ticker.build(1.0 + PERIOD) is None
    assert ticker.next_due() == 1.004 + PERIOD
    assert ticker.build(1.004 + PERIOD) is not None and carried(ticker) == ["la1"]
    ticker.sent(1.004 + PERIOD)
    spacing.ticked(ticker.carried(), ticker, 1.004 + PERIOD)
    assert ticker.next_due() == 1.004 + 2 * PERIOD
    assert ticker.build(1.004 + 2 * PERIOD) is not None, "its own ticks: its own period"


def test_a_held_stream_leaves_the_streams_after_it_in_the_tick():
    spacing = FollowSpacing()
    ticker = stream_ticker(spacing)
    sent(spacing, command_follow(spacing, "la1"), 1.003)
    ticker.update(FollowingDriver("la1", 1), 900, 1.004)  # first in the ticker, held
    ticker.update(FollowingDriver("la2", 2), 900, 1.004)
    assert ticker.build(1.005) is not None and carried(ticker) == ["la2"]


def test_a_buss_streams_keep_its_planners_spacing():
    planner = BusPlanner(TIMING)
    driver = FollowingDriver("la1", 1)
    FollowStreams(planner, BusCounters(0.0), {"la1": driver}).start(driver, 900, 1.0)
    (ticker,) = planner.tickers
    assert isinstance(planner.spacing, FollowSpacing) and ticker.spacing is planner.spacing


def test_a_stream_joining_a_running_ticker_is_left_out_of_its_ticks_until_its_period():
    spacing = FollowSpacing()
    ticker = stream_ticker(spacing)
    ticker.update(FollowingDriver("la2", 2), 900, 1.0)
    sent(spacing, command_follow(spacing, "la1"), 1.003)
    ticker.update(FollowingDriver("la1", 1), 900, 1.004)
    assert ticker.build(1.005).wire == silent_request(6).wire and carried(ticker) == ["la2"]
    ticker.sent(1.005)
    assert ticker.build(1.015) is not None and carried(ticker) == ["la2", "la1"]


def test_a_trajectory_taking_a_device_from_its_stream_skips_a_slot_within_the_period():
    spacing, stream = FollowSpacing(), object()
    la1 = InspireLaDriver("la1", 1)
    la1.online = True
    ticker = TrajectoryTicker(InspireLaDriver, PERIOD, 2.0, BusCounters(0.0), spacing=spacing)
    ticker.add(la1, lambda t_s: {"position": round(1000 + 1000 * t_s)})
    spacing.ticked([la1], stream, 2.0 - 0.004)  # the stream's last tick, 4 ms before slot 0
    assert ticker.build(2.0) is None, "slot 0 passes without a frame"
    due = ticker.next_due()
    assert due >= 2.0 - 0.004 + PERIOD and "la1" in ticker.playing
    request = ticker.build(due)
    assert request is not None and request.frame.position_raw == round(1000 + 1000 * ticker.grid_s)
