"""What a bus thread does with the work other threads hand it: a command judged and planned,
an e-stop, a reset, a scan, a stream started; and every stream, trajectory and waiting command
ended at once (an e-stop, a bus lost, the shutdown).

Rules of this file: bus thread only (the runner calls it from its inbox and its loop); each
outcome goes to the job's future (``outcomes``), a refusal as the refusal, a driver's bug as
``internal`` with its traceback logged, and the bus goes on. An e-stop does before its first
frame only what that frame needs (every driver latched, the waiting commands taken out); the
rest of what it ends, with the events and answers that tell it, comes after the frame
(``end_estopped``): the bus threads sharing an interpreter take turns on that Python, so
every bus's frame would wait for each one's (docs/performance.md, "An e-stop's frame first").
A command's follow-mode targets (an Inspire LA's ``follow``, ``group_follow``), which the
manual takes at a fixed period, are refused (``busy``, nothing sent) for a device that a
follow stream or a trajectory follows (its ticks keep the period: the client puts targets on
the follow key instead), and for one sent such a target less than its follow period before
(by a command, or by the last tick of a stream or a trajectory), or whose command carrying
one still waits to go out (``_check_follow_mode``): the period is counted from when that
target went on the wire, not from when it was planned (``spacing``). Any other command that
would move a device a client's follow stream drives is refused ``busy`` too (the next tick
would overwrite its target, and the stream's stop once it ended: ``_check_streams``), and one
that stops a device on a stream or a ramp ends it once the stop is queued (its next tick
would undo the stop), unless the stop is that ramp (to 0, at the joint's max_acceleration).
A one-shot speed that would be such a ramp is refused ``busy`` for a device that plays (a
trajectory, or a base's drive): the ramp's ticks and the play's would take turns setting its
speed, and the play's next would jump back past the ramp's acceleration. A stop (0) is no
ramp then, nor while the motor is not known to be on: it goes as it is (``_speed_ramp``).
"""

from __future__ import annotations

import itertools
import logging
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from typing import Any

from busgate.errors import BusgateError, BusUnavailableError, BusyError, CommandError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.owner import BusOwner
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver, Effect, Follows
from busgate.gateway.scheduler import outcomes
from busgate.gateway.scheduler.authority import Authority
from busgate.gateway.scheduler.devices import estop_changed, estop_states, tell_unsent
from busgate.gateway.scheduler.planner import CLIENT_SHARE, EVERY_DEVICE, BusPlanner, Job
from busgate.gateway.scheduler.plays import ESTOP, Plays
from busgate.gateway.scheduler.streams import FollowStreams

log = logging.getLogger(__name__)


def safe_stops(drivers: Iterable[Driver]) -> list[Request]:
    """Every driver's safe stop (each latched), taken in rounds: every device's first request
    (a ZLAC706's 0 rpm) before any device's second (its release), so that the wheels of a
    base stop together rather than one after the other's two exchanges."""
    rounds = itertools.zip_longest(*(driver.safe_stop() for driver in drivers))
    return [request for round_ in rounds for request in round_ if request is not None]


class BusWork:
    """The bus thread's handling of what it was handed (the rules above)."""

    def __init__(
        self,
        name: str,
        owner: BusOwner,
        drivers: dict[str, Driver],
        planner: BusPlanner,
        streams: FollowStreams,
        plays: Plays,
        state_of: Callable[[str], dict[str, Any] | None],
    ) -> None:
        self.name = name
        self.owner = owner
        self.drivers = drivers
        self.authority = Authority(name, drivers)
        self.counters: BusCounters = owner.counters
        self.planner = planner
        self.streams = streams
        self.plays = plays
        self.state_of = state_of
        #: An e-stop's ends are still to come (``end_estopped``), with the commands it took out.
        self._estop_ending = False
        self._estop_dropped: list[Job] = []

    def plan_scan(self, requests: list[Request], start_by: float, future: Future) -> None:
        probes = Job(EVERY_DEVICE, deque(requests), keep_going=True, outcomes=[], scan=True)
        probes.start_by, probes.future = start_by, future
        self.queue_job(probes)

    def plan_command(
        self, device: str, command: Any, client: str | None, start_by: float, future: Future
    ) -> None:
        driver = self.drivers.get(device)
        try:
            if driver is None:
                raise CommandError(f"no device {device!r} on bus {self.name}")
            frames = driver.frames_of(command)  # built once: judged, then planned
            effects = driver.effects_of(frames)
            self.authority.check(effects, client, require_claim=command.require_claim)
            self.authority.check_limits(driver.setpoints(frames))
            self.authority.check_ids(driver.id_changes(frames))
            followed = self._check_follow_mode(driver.follow_mode_ids(frames))
            moved = self.authority.addressed(effects)
            self._check_streams(moved)
            estop_before = estop_states([driver])
            playing = self.plays.playing(device)
            ramp = self._speed_ramp(driver, command, playing)
            if ramp is not None and playing:
                raise BusyError(
                    f"{device} plays a trajectory or drives a base, whose next tick sets its "
                    "speed: this speed, ramped at its joint's max_acceleration, would fight it "
                    "for as long as the ramp lasts; cancel the trajectory or stop the base "
                    "first; nothing was sent"
                )
            if ramp is not None:  # a ramp at the joint's max_acceleration (``tickers`` rule 5)
                target, follows = driver.follow_target(ramp), driver.follow_carries(ramp)
                self.start_stream(device, target, now(), follows, ends_on_target=True)
                requests = []
            else:
                requests = driver.plan_frames(command, frames)
            also = {other.name for other in moved if other is not driver}
            reads_only = bool(frames) and all(effect is Effect.READ for _, effect in effects)
            # a stop ends the stream or ramp its device is on (its next tick would undo it),
            # unless the stop became that ramp (to 0 at the joint's max_acceleration)
            stopped = [
                d.name
                for d in self.authority.addressed(effects, Effect.STOP)
                if self.streams.following(d.name) and not (ramp is not None and d is driver)
            ]
        except BusgateError as exc:
            outcomes.settle(future, error=exc)
            return
        except Exception as exc:  # a driver bug: answered ``internal``, the bus goes on
            log.exception("bus %s: planning %r for %s failed", self.name, command, device)
            outcomes.settle(future, error=exc)
            return
        job = Job(
            device,
            deque(requests),
            start_by=start_by,
            future=future,
            also_moves=tuple(also),
            reads_only=reads_only,
            client=client or "",
        )
        job.estop_before = estop_changed(estop_before, [driver])
        self.planner.spacing.commanded(followed, job)
        if self.queue_job(job):  # taken: ended behind it (its stop goes first, then the stream's)
            for name in stopped:
                self.streams.end(name, "stopped by a command")

    def _check_follow_mode(self, ids: frozenset[int]) -> list[str]:
        """Refuse follow-mode targets for the devices of ``ids`` that a stream or a trajectory
        follows, that were sent one less than a follow period ago, or whose command carrying
        one waits to go out; the names of the devices they go to, noted once the command is
        planned."""
        if not ids:
            return []
        moment = now()
        followed = [d for d in self.drivers.values() if d.device_id in ids]
        for driver in followed:
            if self.streams.following(driver.name) or self.plays.playing(driver.name):
                raise BusyError(
                    f"{driver.name} is followed by a stream or a trajectory, whose ticks keep "
                    "the manual's fixed period: put its targets on its follow key; nothing "
                    "was sent"
                )
            sent = self.planner.spacing.last(driver.name)
            if sent is None:
                last = "the command carrying the last one still waits to go out"
            elif moment - sent < driver.follow_period_s:
                last = f"one was sent {(moment - sent) * 1000:.1f} ms ago"
            else:
                continue
            raise BusyError(
                f"{driver.name} takes a follow-mode target once every "
                f"{driver.follow_period_s * 1000:g} ms (its follow period: the manual's "
                f"fixed period), and {last}; nothing was sent"
            )
        return [driver.name for driver in followed]

    def _check_streams(self, moved: list[Driver]) -> None:
        """Refuse (``busy``, nothing sent) a one-shot target for a device ``moved`` whose
        follow stream runs: its next tick would overwrite it, and its stop when it ends."""
        for driver in moved:
            if self.streams.fed(driver.name):
                raise BusyError(
                    f"{driver.name} follows a stream (targets put on its follow key), whose next "
                    "tick would overwrite this target: put it on the follow key, or end the "
                    'stream first ({"op":"end_follow"}); nothing was sent'
                )

    def queue_job(self, job: Job) -> bool:
        """Queue ``job``, or answer it at once (nothing to send); ``False`` when refused (its
        bus down, the queue full), answered so."""
        if not self.owner.is_open:
            tell_unsent(job, self.drivers)
            outcomes.fail(job, BusUnavailableError(f"bus {self.name} is down"))
            return False
        if not job.requests:
            outcomes.complete(job, self.state_of)
            return True
        if not self.planner.push_command(job):
            self.counters.busy_commands += 1
            why = (
                f"client {job.client!r} has {CLIENT_SHARE} commands waiting already"
                if self.planner.share_taken(job.client)
                else "command queue full"
            )
            tell_unsent(job, self.drivers)
            outcomes.fail(job, BusyError(f"bus {self.name}: {why}; nothing was sent"))
            return False
        return True

    def plan_estop(self, future: Future) -> None:
        """The e-stop ahead of everything, with only what must come before its first frame:
        each driver latched (nothing it is asked next moves it), the waiting commands taken
        out. What else it ends is ended once that frame is out (``end_estopped``)."""
        # Each driver latches its e-stop first: a trajectory's watcher (another thread) that
        # sees its play ended sees the device e-stopped too, and tells it as the e-stop.
        requests = safe_stops(self.drivers.values())
        self._estop_dropped.extend(self.planner.drop_commands(keep_reads=True))
        self._estop_ending = True
        # The job's own future, which no caller holds, so none can cancel it (``outcomes``
        # rule 2): each e-stop that joins the job waiting (``push_estop``) gets its outcome.
        carrier = self.planner.push_estop(
            Job(EVERY_DEVICE, deque(requests), keep_going=True, future=Future())
        )
        assert carrier.future is not None
        if self.owner.is_open:
            outcomes.pass_on(carrier.future, future)
        else:  # answered now, not held (with what joins it) for as long as the bus is down
            down = f"bus {self.name} is down: the e-stop goes to its devices once it is back"
            outcomes.settle(future, error=BusUnavailableError(down))

    def end_estopped(self) -> None:
        """What an e-stop planned (``plan_estop``) ends: every stream and trajectory, and the
        commands it took out answered ``estopped``; once, when its first exchange is over or
        anything else ends everything first."""
        if not self._estop_ending:
            return
        self._estop_ending = False
        dropped, self._estop_dropped = self._estop_dropped, []
        self.streams.end_all("estop")
        self.plays.end_all(ESTOP)
        cancelled = outcomes.cancelled_by_estop()
        for job in dropped:
            outcomes.fail(job, cancelled)

    def end_everything(self, streams_why: str, plays_why: str, jobs_error: BusgateError) -> None:
        """Every stream and trajectory ended, every command waiting failed with
        ``jobs_error``: a bus lost, the shutdown (an e-stop's own ends first, as its)."""
        self.end_estopped()
        self.streams.end_all(streams_why)
        self.plays.end_all(plays_why)
        for job in self.planner.drop_commands():
            tell_unsent(job, self.drivers)
            outcomes.fail(job, jobs_error)

    def plan_reset(
        self, device: str | None, start_by: float, future: Future, skip: frozenset[str]
    ) -> None:
        if device is None:
            drivers = [d for name, d in self.drivers.items() if name not in skip]
        else:
            drivers = [self.drivers[device]]
        estop_before = estop_states(drivers)
        requests = deque(r for driver in drivers for r in driver.reset_estop())
        # Every device's frames go, whatever one silent device does (as an e-stop's).
        job = Job(
            device or EVERY_DEVICE,
            requests,
            keep_going=device is None,
            start_by=start_by,
            future=future,
        )
        job.estop_before = estop_changed(estop_before, drivers)
        self.queue_job(job)

    def start_stream(
        self,
        device: str,
        target: Any,
        moment: float,
        follows: Follows,
        *,
        ends_on_target: bool = False,
    ) -> None:
        """A stream of ``target``s that ``follows`` positions or speeds, started or fed; a
        target judged before its device's mode changed is dropped, told as a refusal (a
        speed must never go out as a position)."""
        driver = self.drivers.get(device)
        if driver is None or not self.owner.is_open:
            return
        if driver.estopped:  # e-stopped since its target was judged: no motion (authority 4)
            refusal = driver.estopped_error()
            driver.emit("command_refused", code=refusal.code, message=str(refusal))
            return
        if driver.follows != follows:
            now_follows = "nothing" if driver.follows is None else f"{driver.follows}s"
            message = (
                f"{device} follows {now_follows} now (its mode changed since this {follows} "
                "target was judged); nothing was sent"
            )
            driver.emit("command_refused", code="bad_command", message=message)
            return
        self.streams.start(driver, target, moment, ends_on_target=ends_on_target)

    @staticmethod
    def _speed_ramp(driver: Driver, command: Any, playing: bool) -> dict[str, Any] | None:
        """The follow payload of the ramp a one-shot speed becomes on a velocity joint with a
        ``max_acceleration`` (its family's speed command, ``JointDeclaration.turn``), or
        ``None``: the command is planned as it is. A stop (0) goes as it is while the motor
        is not known to be on (a base's 0 rpm before its enable; a ramp would run on the
        drive's preset) or while the device plays (the play's next tick overrides it, as a
        move's)."""
        joint = driver.joint
        turn, field = joint.declaration.turn, joint.declaration.follow_velocity
        if joint.type != "velocity" or joint.max_acceleration is None or turn is None:
            return None
        op, value = turn
        if field is None or getattr(command, "op", None) != op:
            return None
        speed = getattr(command, value)
        if speed == 0 and (playing or not driver.turning_on):
            return None
        return {field: speed}
