"""The trajectories one bus plays: which ticker carries each device, and how a device leaves
one (the end of its trajectory, a replacement, a cancel or an abort).

Rules of this file:

1. Bus thread only. Other threads (the API, the feedback, the next play) read ``playing``,
   ``commanded``, ``held`` and ``refusal`` from a ``PlaysView``, a snapshot the bus thread
   publishes whole (one assignment) after every change, never from its live tables; then it
   calls ``on_view`` (a bus worker's mirror is woken by it: it sends each new view across).
2. A device plays one trajectory at a time: a new one takes it from its old one (and from its
   follow stream, ended quietly: the trajectory goes on from where the stream was) from the
   next tick on.
3. A device leaves a trajectory holding where it was commanded last (a position device's
   target stops changing at once), or, for a device whose trajectory moves a speed, ramping
   it to 0 over ``RAMP_S`` on its grid, then sending what a stale stream gets (0 rpm).
   E-stop, a lost bus and shutdown take every device out at once; what follows them puts
   every device in its safe state anyway.
4. Once a device left, ``held`` keeps when its last tick went and what it carried: where the
   device is commanded until something newer is known of it (a trajectory that follows
   starts there). So does a device whose follow stream ended (``streams`` rule 3) when its
   driver knows the target of that tick before its telemetry says it
   (``Driver.sent_position_raw``: an Inspire LA's follow frame has no reply, and its state
   tells its target at the next poll, a poll period late at most).
5. A device whose trajectory was ended here, not by its player (its ticker left it out for
   good: it could not take its target; every device was taken out: ``end_all``; or it was
   e-stopped when the play reached its bus, after the play was checked), keeps
   why in ``refusal``, with the start of the trajectory it was playing, until it starts
   another one: that trajectory is over (``busgate.gateway.trajectory.playing`` aborts it,
   even when the device has been enabled again since).
6. A play is checked from where its devices were commanded when it was accepted; a device's
   trajectory or follow stream may send it on until the play reaches its bus (a stream's
   target is known to the checks only at a poll: an Inspire LA's). There, a device whose
   first tick would be a step past its joint's limits in one follow period
   (``Joint.takes_step``, the check of a first point's) from where its trajectory, its
   stream or its last command sent it does not start, and the refusal says why (rule 5):
   the step would reach the device whatever the check saw. A trajectory it played stops as
   rule 3 says; a stream, or a speed of its own command, goes on: the play did not take it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver, Follows
from busgate.gateway.scheduler.planner import BusPlanner, Job
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.tickers import commanded
from busgate.gateway.scheduler.trajectory_ticks import Sampler, TrajectoryTicker

#: How long a speed is ramped to 0 when its device leaves a trajectory early.
RAMP_S = 0.5
#: Why a device left its trajectory in ``end_all`` (rule 5), by what ended them all.
END_ALL = "was stopped with every device of its bus ({why})"
#: What ``end_all`` is told on an e-stop; its refusal is ``ESTOPPED`` (a watcher tells the
#: e-stop by it, whatever a driver's state says at that moment).
ESTOP = "an e-stop"
ESTOPPED = END_ALL.format(why=ESTOP)


@dataclass(frozen=True, slots=True)
class PlaysView:
    """What one bus plays, as its thread last published it (rule 1): never changed once made."""

    #: Device → (seconds from its trajectory's start, target) of its last tick.
    commanded: Mapping[str, tuple[float, Any]] = field(default_factory=dict)
    held: Mapping[str, tuple[float, Any]] = field(default_factory=dict)
    refusals: Mapping[str, tuple[float, str]] = field(default_factory=dict)
    playing: frozenset[str] = frozenset()


class Plays:
    """Starts, feeds and ends the trajectories of the devices of one bus."""

    def __init__(
        self,
        planner: BusPlanner,
        counters: BusCounters,
        drivers: dict[str, Driver],
        streams: FollowStreams,
    ) -> None:
        self.planner = planner
        self.counters = counters
        self.drivers = drivers
        self.streams = streams
        self._tickers: dict[str, TrajectoryTicker] = {}  # device → its ticker
        #: Device → (the start of the trajectory it was playing, why it was ended) (rule 5).
        self._refusals: dict[str, tuple[float, str]] = {}
        self._held: dict[str, tuple[float, Any]] = {}  # device → its last tick (rule 4)
        #: The snapshot other threads read (rule 1), and what is told of each new one.
        self.view = PlaysView()
        self.on_view: Callable[[], None] = _nothing
        streams.on_left = self._stream_left

    def playing(self, device: str) -> bool:
        """Any thread: ``device`` is in a trajectory (its ticks carry it)."""
        return device in self.view.playing

    def commanded(self, device: str) -> tuple[float, Any] | None:
        """Any thread: (seconds from its trajectory's start, target) of ``device``'s last tick."""
        return self.view.commanded.get(device)

    def held(self, device: str) -> tuple[float, Any] | None:
        """Any thread: (bus time, target) of the last tick of ``device`` once it left its
        trajectory (rule 4)."""
        return self.view.held.get(device)

    def refusal(self, device: str) -> tuple[float, str] | None:
        """Any thread: (its start, why) of the trajectory of ``device`` ended here (rule 5)."""
        return self.view.refusals.get(device)

    def start(self, samplers: dict[str, Sampler], start: float) -> None:
        """Play each device's sampler from ``start`` (bus clock) on (rule 2)."""
        for name, sample in samplers.items():
            driver = self.drivers[name]
            self._refusals.pop(name, None)
            if driver.estopped:  # e-stopped since the play was checked: it does not start
                self._leave(name)
                self._refusals[name] = (start, ESTOPPED)
                continue
            too_far = self._first_step_past_limits(driver, sample, start)
            if too_far is not None:  # rule 6: its trajectory stops, anything else goes on
                if name in self._tickers:
                    self.stop(name, speed=driver.follow_carries(sample(0.0)) == "velocity")
                self._refusals[name] = (start, too_far)
                continue
            self._leave(name)
            self.streams.drop(name, "trajectory")
            ticker = self._ticker_for(driver, start)
            ticker.add(driver, sample)
            self._tickers[name] = ticker
        self._publish()

    def stop(self, device: str, *, speed: bool) -> None:
        """``device`` leaves its trajectory (rule 3): it holds, or its speed ramps to 0."""
        ticker = self._tickers.get(device)
        if ticker is None:
            return
        last = ticker.commanded.get(device)
        driver = self.drivers[device]
        field = driver.joint_declaration().follow_velocity if speed else None
        if field is None or last is None:  # a position, or no speed its family streams
            self._leave(device)
            self._publish()
            return
        from_s, value = last
        ticker.add(driver, _ramp_to_zero(field, from_s, value))
        ticker.ramping[device] = from_s + RAMP_S  # on this ticker's grid until then

    def end_all(self, why: str) -> None:
        """Every device out at once (rule 3: an e-stop, a lost bus, shutdown: ``why``)."""
        for name, ticker in list(self._tickers.items()):
            self._refusals[name] = (ticker.start, END_ALL.format(why=why))
            self._leave(name)
        self._publish()

    def after_tick(self, ticker: TrajectoryTicker) -> None:
        """A ticker's slot went by: devices it left out leave (rule 5); devices whose ramp is
        done leave, with their stale-stream requests (0 rpm)."""
        while ticker.refused:
            name, reason = ticker.refused.popitem()
            self._refusals[name] = (ticker.start, f"could not take its target: {reason}")
            self._leave(name)
        for name, until in list(ticker.ramping.items()):
            commanded = ticker.commanded.get(name)
            if commanded is not None and commanded[0] >= until:
                driver = ticker.playing[name].driver
                self._leave(name)
                requests = driver.stale_stream()
                if requests:
                    self.planner.push_stop(Job(name, deque(requests)))
        self._publish()

    def _first_step_past_limits(self, driver: Driver, sample: Sampler, start: float) -> str | None:
        """Why ``driver``'s first tick of ``sample`` may not go: a step past its joint's
        limits from where its trajectory, its follow stream or its last command sent it
        (rule 6); ``None`` when it may."""
        name, joint = driver.name, driver.joint
        payload = sample(0.0)
        carries = driver.follow_carries(payload)
        ticker = self._tickers.get(name)
        if ticker is not None:
            last = ticker.commanded.get(name)
            same = driver.follow_carries(ticker.playing[name].sample(0.0)) == carries
            was, source = (last[1] if last is not None and same else None), "its trajectory"
        elif (sent := self.streams.sent(name, carries)) is not None:
            was, source = sent, "its follow stream"
        else:  # a command's target is known to the checks as soon as to the bus: no race
            was, source = _last_commanded(driver, carries, start), "its last command"
        [first] = payload.values()
        speed = carries == "velocity"
        if was is None or joint.takes_step(first - was, driver.follow_period_s, speed=speed):
            return None
        if speed:
            step, unit, limit = joint.velocity_si(first - was), f"{joint.unit}/s", "acceleration"
        else:
            step, unit, limit = (first - was) * joint.scale, joint.unit, "velocity"
        return (
            f"would step {step:+g} {unit} at its first tick from where {source} had sent it "
            f"when the play reached its bus, past its max_{limit} in one follow period"
        )

    def _stream_left(self, driver: Driver, at: float) -> None:
        """``driver``'s follow stream ended, its last tick gone at ``at`` (rule 4)."""
        sent = driver.sent_position_raw()
        if sent is not None and driver.name not in self._tickers:
            self._held[driver.name] = (at, sent)
            self._publish()

    def _publish(self) -> None:
        """A new snapshot for the other threads (rule 1): copies, one assignment."""
        commanded = {}
        for name, ticker in self._tickers.items():
            last = ticker.commanded.get(name)
            if last is not None:
                commanded[name] = last
        self.view = PlaysView(
            commanded, dict(self._held), dict(self._refusals), frozenset(self._tickers)
        )
        self.on_view()

    def _leave(self, device: str) -> None:
        ticker = self._tickers.pop(device, None)
        if ticker is None:
            return
        last, sent_at = ticker.commanded.get(device), ticker.last_sent
        if last is not None and sent_at is not None:
            self._held[device] = (sent_at, last[1])  # rule 4
        ticker.remove(device)
        ticker.ramping.pop(device, None)
        if not ticker.playing and ticker in self.planner.tickers:
            self.planner.tickers.remove(ticker)

    def _ticker_for(self, driver: Driver, start: float) -> TrajectoryTicker:
        period = driver.follow_period_s
        for ticker in self.planner.tickers:
            if (
                isinstance(ticker, TrajectoryTicker)
                and ticker.driver_class is type(driver)
                and ticker.period_s == period
                and ticker.start == start
                and ticker.has_room(driver)
            ):
                return ticker
        sibling = next(
            (
                t
                for t in self.planner.tickers
                if isinstance(t, TrajectoryTicker) and t.period_s == period and t.start == start
            ),
            None,
        )
        group = sibling.group if sibling is not None else None  # ``trajectory_ticks`` rule 6
        ticker = TrajectoryTicker(
            type(driver), period, start, self.counters, self.after_tick, group, self.planner.spacing
        )
        self.planner.tickers.append(ticker)
        return ticker


def _last_commanded(driver: Driver, carries: Follows, moment: float) -> float | None:
    """Where ``driver``'s last command sent it, as a value of the kind a play ``carries``;
    ``None`` when its mode takes another kind, or for a speed its telemetry does not know
    (the checks took its measured speed then)."""
    if driver.follows != carries:
        return None
    if carries == "velocity":  # ``commanded`` takes 0 for a speed not known: a stream's start
        return driver.telemetry(moment).get(driver.joint.declaration.target_speed_rpm or "")
    return commanded(driver, moment)


def _ramp_to_zero(field: str, from_s: float, speed: float) -> Sampler:
    """A speed ramp from ``speed`` at ``from_s`` to 0 over ``RAMP_S``, in the follow payload's
    ``field`` (the family's ``follow_velocity``)."""

    def sample(t_s: float) -> dict[str, Any]:
        return {field: speed * max(0.0, 1 - (t_s - from_s) / RAMP_S)}

    return sample


def _nothing() -> None:
    """``on_view`` while nobody asked to be told (a bus in the gateway's own process)."""
