"""Trajectories played by the gateway: ``play``, ``cancel`` and ``status`` on
``<prefix>/<gw>/trajectory``, and each running trajectory watched until its result.

Rules of this file:

1. A ``play`` is refused, with a stable code and nothing moving, when: the points are
   malformed (``bad_command``; too many: ``out_of_range``); a device is not on this gateway
   (``unknown_device``) or has no stream of the trajectory's values (``bad_command``); one is
   claimed by another client (``claimed``) or, with ``require_claim``, not by its client
   (``not_claimed``), e-stopped (``estopped``), offline
   (``device_timeout``) or on a bus that is down (``bus_unavailable``); a value of its path
   would be outside its device's range (``out_of_range``: the whole path is bounded segment
   by segment, ``trajectory.bounds``, so overshoot between points is caught at a cost that
   grows with the points, not with the ticks); ``start_at`` is past, too close to now for
   the buses, or over an hour ahead (``out_of_range``); the ticks would need more of a bus's
   time than it has (``out_of_range``, naming the bus); its ``id`` is that of a trajectory
   another client is playing (``bad_command``, naming the id).
2. Accepted, each device's bus samples it on the shared grid (``scheduler.trajectory_ticks``)
   from the one start time; a device of another running trajectory is taken from it, whose
   result is ``replaced``, as is a trajectory of the same client under the same id.
3. Watched on the loop's thread (``tick``), a running trajectory ends ``succeeded`` once every
   device has been sent its last point's value (the first tick at or after it) and is within
   its goal tolerance (at once without one), else is ``aborted`` (each device holding, a speed
   ramped to 0) on: an e-stop, a device offline, its client gone, a claim it played under
   lost, a device claimed by another client, a device its bus took out of it (it could no
   longer take its target, or every device was stopped: ``Plays.refusal``), a measured value
   off the path by more than its path tolerance (compared with the path at the moment the
   value was read), or no goal by ``goal_time_s`` after the last point. All but the
   tolerances are watched from the moment it is accepted, before its start too. ``cancel``
   ends it ``canceled`` the same way.
4. Feedback goes out at least ``1 / FEEDBACK_EVERY_S`` times a second on
   ``<prefix>/<gw>/trajectory/<id>/feedback``, on a grid of that period from the first (a
   round of the loop that comes late does not push the later ones back); the result once,
   there and as an event.
5. ``command`` may run long (a 1 MiB payload is parsed and checked): it runs on a lane's
   thread (``trajectory_lanes``), never on zenoh's or the loop's; the running table is shared
   under a lock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from busgate.errors import BusgateError, CommandError, RefusedError
from busgate.gateway.api.commands import GatewayApi, decode_object, ok_reply
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent, Driver, Effect
from busgate.gateway.scheduler.plays import ESTOPPED
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.bounds import value_refused
from busgate.gateway.trajectory.interpolation import Path, paths_of, sent
from busgate.schemas.trajectory import (
    MAX_TRAJECTORY_PAYLOAD,
    TRAJECTORY_COMMAND_ADAPTER,
    TrajectoryCancel,
    TrajectoryPlay,
)

FEEDBACK_EVERY_S = 0.1
#: With no ``start_at``: how far ahead the trajectory starts (every bus takes it in by then).
LEAD_S = 0.1
#: A ``start_at`` nearer than this cannot be met by every bus: refused.
MIN_LEAD_S = 0.02
MAX_AHEAD_S = 3600.0
#: The share of a bus's time a trajectory's ticks may take, beside what it does already.
BUS_SHARE = 0.9

#: How long past its last point (and ``goal_time_s``) a trajectory waits for the tick that
#: sends each device that point's value (the next slot, a period at most) before it is
#: aborted: a bus that stopped ticking without any other reason to abort.
LAST_TICK_WAIT_S = 1.0

#: Per values field: the follow payload's key and the telemetry's measured field.
FIELDS = {"positions": ("position", "position"), "rpms": ("rpm", "speed_rpm")}


@dataclass
class Member:
    """One device of a running trajectory."""

    name: str
    runner: BusRunner
    driver: Driver
    path: Path
    key: str  # the follow payload's key: position or rpm
    measured_key: str
    path_tolerance: float | None
    goal_tolerance: float | None
    claimed: bool  # its client held the device's claim when it started

    def sample(self, t_s: float) -> dict[str, Any]:
        return self.payload(self.path.at(t_s))

    def payload(self, value: float) -> dict[str, Any]:
        """The follow payload that sends ``value``."""
        return {self.key: sent(value) if self.key == "position" else value}

    def takes(self, value: float) -> bool:
        """Whether the device takes ``value`` as its target."""
        try:
            self.driver.follow_target(self.payload(value))
        except (CommandError, RefusedError):
            return False
        return True

    def measured(self) -> tuple[float, float] | None:
        """(wall time read, value) of the device's last published state."""
        state = self.runner.states.get(self.name) or {}
        value, read = state.get(self.measured_key), state.get("ts")
        return None if value is None or read is None else (read, value)


@dataclass
class Running:
    id: str
    client: str | None
    members: list[Member]
    start_at: float  # wall
    start_bus: float  # the same moment, bus clock: the start its devices' tickers have
    end_s: float
    goal_time_s: float
    next_feedback: float = 0.0
    errors: dict[str, float | None] = field(default_factory=dict)

    @property
    def end_at(self) -> float:
        return self.start_at + self.end_s

    def summary(self, moment: float) -> dict[str, Any]:
        t_s = max(0.0, moment - self.start_at)
        return {
            "id": self.id,
            "client": self.client,
            "devices": [m.name for m in self.members],
            "start_at": self.start_at,
            "end_at": self.end_at,
            "t_s": t_s,
            "progress": 1.0 if self.end_s == 0 else min(1.0, t_s / self.end_s),
        }


class Trajectories:
    """The trajectory key of one gateway."""

    def __init__(
        self,
        api: GatewayApi,
        base: str,
        publish: Callable[[str, dict[str, Any]], None],
        on_event: Callable[[DeviceEvent], None],
    ) -> None:
        self.api = api
        self.base = base
        self.publish = publish
        self.on_event = on_event
        self._lock = threading.Lock()
        self._running: dict[str, Running] = {}

    # -- commands (a worker thread: rule 5) ------------------------------------------------------

    def command(self, payload: bytes) -> dict[str, Any]:
        """The reply to one query on the trajectory key."""
        fields = decode_object(payload, limit=MAX_TRAJECTORY_PAYLOAD)
        request = TRAJECTORY_COMMAND_ADAPTER.validate_python(fields)
        if isinstance(request, TrajectoryPlay):
            return self.play(request)
        if isinstance(request, TrajectoryCancel):
            return self.cancel(request.id)
        with self._lock:
            running = [r.summary(time.time()) for r in self._running.values()]
        return ok_reply(trajectories=running)

    def play(self, request: TrajectoryPlay) -> dict[str, Any]:
        members = self._members(request)
        start_at = self._start_at(request.start_at)
        self._check_buses(members)
        start_bus = now() + (start_at - time.time())
        running = Running(
            request.id,
            request.client,
            members,
            start_at,
            start_bus,
            max(m.path.end_s for m in members),
            request.goal_time_s,
        )
        with self._lock:
            self._check_id(request)
            taken = {m.name for m in members}
            for other in list(self._running.values()):
                if other.id == request.id or taken & {m.name for m in other.members}:
                    self._end(other, "replaced", keep=frozenset(taken))
            self._running[request.id] = running
        for runner in {m.runner for m in members}:
            runner.play({m.name: m.sample for m in members if m.runner is runner}, start_bus)
        self._event(running, "trajectory_started", start_at=start_at, end_at=running.end_at)
        return ok_reply(
            trajectory={
                "id": request.id,
                "start_at": start_at,
                "end_at": running.end_at,
                "devices": request.devices,
            }
        )

    def cancel(self, trajectory: str) -> dict[str, Any]:
        with self._lock:
            running = self._running.get(trajectory)
            if running is None:
                raise RefusedError("bad_command", f"no trajectory {trajectory!r} is running")
            self._end(running, "canceled")
        return ok_reply(canceled=trajectory)

    # -- watching (the loop's thread: rules 3 and 4) ---------------------------------------------

    def tick(self) -> None:
        """Feedback, aborts and results of every running trajectory, at this moment."""
        moment = time.time()
        with self._lock:
            for running in list(self._running.values()):
                verdict = self._verdict(running, moment)
                if verdict is not None:
                    self._end(running, *verdict)
                elif moment >= running.next_feedback:
                    due = running.next_feedback  # rule 4: on the grid, unless a period behind
                    since = due if moment - due < FEEDBACK_EVERY_S else moment
                    running.next_feedback = since + FEEDBACK_EVERY_S
                    self.publish(self._feedback_key(running), self._feedback(running, moment))

    def client_left(self, client: str) -> None:
        with self._lock:
            for running in list(self._running.values()):
                if running.client == client:
                    self._end(running, "aborted", reason="client gone")

    # -- play's checks (rule 1) -------------------------------------------------------------------

    def _members(self, request: TrajectoryPlay) -> list[Member]:
        key, measured_key = FIELDS[request.values_field]
        paths = paths_of(request, [self._start_value(d, key) for d in request.devices])
        members = []
        for index, (name, path) in enumerate(zip(request.devices, paths, strict=True)):
            runner, driver = self._device(name)
            self._check_device(runner, driver, request.client, request.require_claim)
            member = Member(
                name,
                runner,
                driver,
                path,
                key,
                measured_key,
                _nth(request.path_tolerance, index),
                _nth(request.goal_tolerance, index),
                request.client is not None and _holds(runner, name, request.client),
            )
            _check_path(member)
            members.append(member)
        return members

    def _check_id(self, request: TrajectoryPlay) -> None:
        """A running trajectory's id is its client's (rule 1): under the lock."""
        other = self._running.get(request.id)
        if other is not None and other.client != request.client:
            raise RefusedError(
                "bad_command",
                f"trajectory id {request.id!r} is taken by a trajectory another client plays: "
                "choose another id",
            )

    def _device(self, name: str) -> tuple[BusRunner, Driver]:
        found = self.api.devices.get(name)
        if found is None:
            raise RefusedError(
                "unknown_device",
                f"no device {name!r} on gateway {self.api.name}: a trajectory plays the "
                "devices of one gateway",
            )
        return found

    def _check_device(
        self, runner: BusRunner, driver: Driver, client: str | None, require_claim: bool
    ) -> None:
        if not runner.owner.is_open:
            raise RefusedError("bus_unavailable", f"bus {runner.name} of {driver.name} is down")
        runner.authority.judge(driver.name, Effect.MOTION, client, require_claim=require_claim)
        if not driver.online:
            raise RefusedError("device_timeout", f"{driver.name} is offline: it does not answer")

    def _start_value(self, name: str, key: str) -> float:
        """Where ``name`` is commanded: its trajectory's last tick, while it plays, or once it
        left while nothing was read from it since; else its state's target, else its measured
        value (0 when nothing is known)."""
        runner, _ = self._device(name)
        commanded = runner.plays.commanded(name)
        if commanded is not None:
            return commanded[1]
        state = runner.states.get(name) or {}
        held = runner.plays.held(name)
        if held is not None and not _read_after(state, held[0]):
            return held[1]  # the state was read before that tick: its target is older
        fields = ("target", "position") if key == "position" else ("target_speed_rpm", "speed_rpm")
        known = [float(state[f]) for f in fields if state.get(f) is not None]
        return known[0] if known else 0.0

    def _start_at(self, start_at: float | None) -> float:
        moment = time.time()
        if start_at is None:
            return moment + LEAD_S
        if start_at < moment + MIN_LEAD_S:
            raise RefusedError(
                "out_of_range",
                f"start_at {start_at:.3f} is {moment - start_at:+.3f} s from now: at least "
                f"{MIN_LEAD_S * 1000:.0f} ms ahead, for every bus to meet it",
            )
        if start_at > moment + MAX_AHEAD_S:
            raise RefusedError("out_of_range", f"start_at is over {MAX_AHEAD_S:.0f} s ahead")
        return start_at

    def _check_buses(self, members: list[Member]) -> None:
        """The ticks fit in each bus's time beside what it does already (rule 1)."""
        for runner in {m.runner for m in members}:
            mine = [m for m in members if m.runner is runner]
            load = 0.0
            for driver_class, period in {(type(m.driver), m.driver.follow_period_s) for m in mine}:
                group = [m for m in mine if type(m.driver) is driver_class]
                limit = driver_class.follow_group_limit
                for first in range(0, len(group), limit):
                    chunk = group[first : first + limit]
                    targets = [(m.driver, m.driver.follow_target(m.sample(0.0))) for m in chunk]
                    request = driver_class.follow_request(targets)
                    load += (runner.timing.worst_case(request) + runner.timing.gap_s) / period
            used = runner.statistics().utilisation
            if load + used > BUS_SHARE:
                raise RefusedError(
                    "out_of_range",
                    f"bus {runner.name} has no room: the ticks need {load:.0%} of its time "
                    f"and {used:.0%} is in use (at most {BUS_SHARE:.0%})",
                )

    # -- watching ---------------------------------------------------------------------------------

    def _verdict(self, running: Running, moment: float) -> tuple[str, ...] | None:
        """``(result, reason)`` once ``running`` is over, else ``None`` (rule 3)."""
        for member in running.members:
            driver = member.driver
            if driver.estopped:
                return ("aborted", "estop")
            if not driver.online:
                return ("aborted", f"{member.name} offline")
            claim = _claim_problem(member, running.client)
            if claim is not None:
                return ("aborted", claim)
            refused = member.runner.plays.refusal(member.name)
            if refused is not None and refused[0] == running.start_bus:  # not an older one's
                if refused[1] == ESTOPPED:  # (an LA's state may lag its latch: a reply in flight)
                    return ("aborted", "estop")
                return ("aborted", f"{member.name} {refused[1]}")
        t_s = moment - running.start_at
        if t_s < 0:
            return None
        errors = self._errors(running)
        running.errors = errors
        if t_s <= running.end_s:
            for member in running.members:
                error = errors.get(member.name)
                tolerance = member.path_tolerance
                if tolerance is not None and error is not None and abs(error) > tolerance:
                    return ("aborted", "path_tolerance")
            return None
        if not all(_sent_last(m) for m in running.members):  # on their way: the next tick
            if t_s > running.end_s + running.goal_time_s + LAST_TICK_WAIT_S:
                return ("aborted", "its last point was not sent")
            return None
        if all(_within(errors.get(m.name), m.goal_tolerance) for m in running.members):
            return ("succeeded",)
        if t_s > running.end_s + running.goal_time_s:
            return ("aborted", "goal_tolerance")
        return None

    def _errors(self, running: Running) -> dict[str, float | None]:
        """Each device's measured value minus the path at the moment it was read."""
        errors: dict[str, float | None] = {}
        for member in running.members:
            measured = member.measured()
            if measured is None or measured[0] < running.start_at:
                errors[member.name] = None
                continue
            read, value = measured
            errors[member.name] = value - member.path.at(read - running.start_at)
        return errors

    def _feedback(self, running: Running, moment: float) -> dict[str, Any]:
        t_s = moment - running.start_at
        devices = []
        for member in running.members:
            measured = member.measured()
            commanded = member.runner.plays.commanded(member.name)
            devices.append(
                {
                    "device": member.name,
                    "desired": member.sample(t_s)[member.key],
                    "commanded": None if commanded is None else commanded[1],
                    "measured": None if measured is None else measured[1],
                    "error": running.errors.get(member.name),
                }
            )
        return {"ts": moment, "id": running.id, "t_s": t_s, "devices": devices}

    def _end(self, running: Running, result: str, reason: str | None = None, *,
             keep: frozenset[str] = frozenset()) -> None:  # fmt: skip
        """``running`` is over: its devices (but those another trajectory takes: ``keep``)
        hold or ramp to 0, and its result goes out once (rule 4). Under the lock."""
        if self._running.get(running.id) is running:
            del self._running[running.id]
        for member in running.members:
            if member.name not in keep:
                member.runner.stop_playing(member.name, speed=member.key == "rpm")
        body = {"ts": time.time(), "id": running.id, "result": result,
                "errors": running.errors} | ({"reason": reason} if reason else {})  # fmt: skip
        self.publish(self._feedback_key(running), body)
        self._event(
            running, "trajectory_ended", result=result, **({"reason": reason} if reason else {})
        )

    def _event(self, running: Running, type_: str, **fields: Any) -> None:
        client = {"client": running.client} if running.client else {}
        self.on_event(DeviceEvent("*", type_, {"id": running.id, **client, **fields}))

    def _feedback_key(self, running: Running) -> str:
        return f"{self.base}/trajectory/{running.id}/feedback"


def _within(error: float | None, tolerance: float | None) -> bool:
    """No tolerance, or a known error within it."""
    return tolerance is None or (error is not None and abs(error) <= tolerance)


def _nth(values: list[float] | None, index: int) -> float | None:
    return None if values is None else values[index]


def _read_after(state: dict[str, Any], moment: float) -> bool:
    """Whether ``state`` was read (its ``ts``, wall clock) after ``moment`` (bus clock)."""
    read = state.get("ts")
    return read is not None and now() - (time.time() - read) > moment


def _sent_last(member: Member) -> bool:
    """Whether ``member``'s bus has sent it its last point's value (a tick at or after it)."""
    commanded = member.runner.plays.commanded(member.name)
    return commanded is not None and commanded[0] >= member.path.end_s


def _claim_problem(member: Member, client: str | None) -> str | None:
    """Why ``client``'s trajectory may no longer move ``member``: the claim it played under
    lapsed or went, or another client claimed the device; ``None`` when it may."""
    runner, device = member.runner, member.name
    if member.claimed and not _holds(runner, device, client):
        return f"claim on {device} lost"
    try:
        runner.authority.judge(device, Effect.SETTING, client)  # the claim (an e-stop: above)
    except BusgateError as exc:
        return str(exc)
    return None


def _holds(runner: BusRunner, device: str, client: str | None) -> bool:
    """Whether ``client`` holds ``device``'s claim now."""
    try:
        runner.authority.judge(device, Effect.SETTING, client, require_claim=True)
    except BusgateError:
        return False
    return True


def _check_path(member: Member) -> None:
    """Every value of the path is in the device's range (rule 1), else the device's own
    refusal of a value the path reaches."""
    refused = value_refused(member.path, member.takes)
    if refused is not None:
        member.driver.follow_target(member.payload(refused))  # raises, saying why
