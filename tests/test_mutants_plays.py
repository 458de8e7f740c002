"""Plays and their limits, by plain calls on a bus never started: a play starts every device
but an e-stopped one, devices played from one start decide together whether a slot is on
time, a device leaves its play holding or ramping as asked, and a position stream carried
past a joint's limit by a late turn stops on it."""

from __future__ import annotations

import pytest

from busgate.gateway.scheduler.limiter import StreamLimiter
from busgate.gateway.scheduler.plays import ESTOPPED
from busgate.gateway.scheduler.trajectory_ticks import TrajectoryTicker
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import parse_config
from tests.test_mutants_base import IdleBase
from tests.test_mutants_scheduler import la_joint, wheel_joint


def turning(_t_s: float) -> dict:
    return {"rpm": 30}


def wheels_in_velocity_mode() -> IdleBase:
    idle = IdleBase()
    for _, driver in idle.api.devices.values():
        driver.mirror({"mode": "velocity", "enabled": True})
    return idle


def tickers(idle: IdleBase) -> list[TrajectoryTicker]:
    return [t for t in idle.runner.planner.tickers if isinstance(t, TrajectoryTicker)]


def test_a_play_starts_every_device_but_an_estopped_one_which_is_told() -> None:
    idle = wheels_in_velocity_mode()
    idle.api.devices["wl"][1].safe_stop()
    plays = idle.runner.plays
    plays.start({"wl": turning, "wr": turning}, 10.0)
    assert plays.playing("wr") and not plays.playing("wl")
    assert plays.refusal("wl") == (10.0, ESTOPPED) and plays.refusal("wr") is None


def test_devices_played_from_one_start_decide_together_whether_a_slot_is_on_time() -> None:
    idle = wheels_in_velocity_mode()
    idle.runner.plays.start({"wl": turning, "wr": turning}, 10.0)
    left, right = tickers(idle)  # a ZLAC706 frame carries one node: a ticker each
    assert left.group is right.group
    apart = wheels_in_velocity_mode()
    apart.runner.plays.start({"wl": turning}, 10.0)
    apart.runner.plays.start({"wr": turning}, 11.0)
    left, right = tickers(apart)
    assert left.group is not right.group


def test_a_device_leaves_its_play_holding_or_ramping_down_as_asked() -> None:
    idle = wheels_in_velocity_mode()
    plays = idle.runner.plays
    plays.start({"wl": turning, "wr": turning}, 10.0)
    for ticker in tickers(idle):  # one slot each: both have a speed commanded
        assert ticker.build(10.0) is not None
        ticker.sent(10.0)
    plays.stop("wl", speed=False)
    plays.stop("wr", speed=True)
    assert not plays.playing("wl")  # holds where its last tick left it
    assert plays.playing("wr")  # ramps to 0 first
    (ramp,) = tickers(idle)
    moment = 10.0
    while plays.playing("wr"):
        moment += ramp.period_s
        assert moment < 12.0, "the ramp never ended"
        assert ramp.build(moment) is not None
        ramp.sent(moment)
    (zero,) = idle.runner.planner.drop_commands()  # the stale stream's 0 rpm, once off it
    assert zero.device == "wr" and [r.frame.value for r in zero.requests] == [0]


def test_a_device_that_joins_a_ticker_after_it_sent_may_leave_before_its_first_tick() -> None:
    config = parse_config({"gateway": {"name": "gw"}, "buses": [{
        "name": "uart0", "transport": "serial", "port": "/dev/null", "baudrate": 921600,
        "devices": [{"name": f"la{n}", "kind": "inspire_la", "id": n} for n in (1, 2)]}]})
    runner = build_bus(config.buses[0])
    plays = runner.plays
    plays.start({"la1": lambda _t: {"position": 900}}, 10.0)
    (ticker,) = [t for t in runner.planner.tickers if isinstance(t, TrajectoryTicker)]
    assert ticker.build(10.0) is not None
    ticker.sent(10.0)
    plays.start({"la2": lambda _t: {"position": 900}}, 10.0)  # one frame carries both
    assert [t for t in runner.planner.tickers if isinstance(t, TrajectoryTicker)] == [ticker]
    plays.stop("la2", speed=False)
    assert not plays.playing("la2") and plays.held("la2") is None  # it never had a tick
    plays.stop("la1", speed=False)
    assert plays.held("la1") == (10.0, 900)


def test_a_position_stream_carried_past_a_limit_stops_on_it_and_starts_again_from_rest():
    """Heading down to 0 and braking, the target turns round late: one more tick at the
    deceleration limit would carry it past 0 (the raw range's low end)."""
    limiter = StreamLimiter(la_joint(max_velocity=0.1, max_acceleration=0.25), 0.01, 0)
    assert limiter.step(99)[0] == 5  # from rest: one tick's change, to the float's last bit
    assert limiter.value == pytest.approx(5, abs=1e-9)
    sent = [5] + [limiter.step(target)[0] for target in (12, 0, 0, 0, 81)]
    assert min(sent) == sent[-1] == 0 and (limiter.value, limiter.rate) == (0, 0.0)
    # from rest at 0.25 m/s²: 5 counts a tick more each tick (5e-6 m a count, 10 ms ticks)
    assert [limiter.step(81)[0] for _ in range(3)] == [5, 15, 30]


def test_each_tick_says_which_limit_held_the_target_back() -> None:
    position = StreamLimiter(la_joint(max_velocity=0.01, max_acceleration=0.25), 0.01, 0)
    ticks = [position.step(2000) for _ in range(4)]
    assert ticks == [(5, "max_acceleration"), (15, "max_acceleration"),  # speeding up
                     (30, "max_acceleration"), (50, "max_velocity")]  # 0.01 m/s: 20 a tick
    speed = StreamLimiter(wheel_joint(max_acceleration=1.0), 0.02, 0.0)
    held = speed.step(100.0)
    assert held[1] == "max_acceleration" and 0 < held[0] < 100
    assert speed.step(held[0] * 1.5) == (held[0] * 1.5, None)  # within a tick's change
