"""Trajectories played by the gateway: ``play``, ``cancel`` and ``status`` on
``<prefix>/<gw>/trajectory``, and each running trajectory watched until its result.

Rules of this file:

1. A ``play`` is refused, with a stable code and nothing moving, by its checks (``checks``),
   when its ``id`` is that of a trajectory another client is playing (``bad_command``), or
   when a device is a wheel of a base that drives it (``busy``: the base never drives on
   one wheel, ``busgate.gateway.base.bases`` rule 3). A play and a base's drive are
   chosen under one lock (``players``), so that neither takes a wheel the other has just
   taken.
2. Accepted, each device's bus samples it on the shared grid (``scheduler.trajectory_ticks``)
   from the one start time; a device of another running trajectory is taken from it, whose
   result is ``replaced``, as is a trajectory of the same client under the same id.
3. Watched on the loop's thread (``tick``), a running trajectory ends when its verdict says
   so (``verdicts``: ``succeeded``, or ``aborted`` and why); ``cancel`` ends it ``canceled``.
4. Feedback goes out at least ``1 / FEEDBACK_EVERY_S`` times a second on
   ``<prefix>/<gw>/trajectory/<id>/feedback``, on a grid of that period from the first (a
   round of the loop that comes late does not push the later ones back); the result once,
   there and as an event. Each device's values are raw, as its path is, and again in its
   joint's SI unit (``joint``), whatever units the play was given in.
5. ``command`` may run long (a 1 MiB payload is parsed and checked): it runs on a lane's
   thread (``lanes``), never on zenoh's or the loop's; the running table is shared
   under a lock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from busgate.errors import RefusedError
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.scheduler.outcomes import cancelled_by_estop
from busgate.gateway.trajectory.checks import check_buses, members_of, start_at_of
from busgate.gateway.trajectory.members import Gateway, Running
from busgate.gateway.trajectory.verdicts import verdict
from busgate.schemas.payload import decode_object, ok_reply
from busgate.schemas.trajectory import (
    MAX_TRAJECTORY_PAYLOAD,
    TRAJECTORY_COMMAND_ADAPTER,
    TrajectoryCancel,
    TrajectoryPlay,
)

FEEDBACK_EVERY_S = 0.1


class Trajectories:
    """The trajectory key of one gateway."""

    def __init__(
        self,
        api: Gateway,
        base: str,
        publish: Callable[[str, dict[str, Any]], None],
        on_event: Callable[[DeviceEvent], None],
        driven_by: Callable[[str], str | None],
    ) -> None:
        self.api = api
        self.base = base
        self.publish = publish
        self.on_event = on_event
        #: The base that drives a device (one of its wheels), if one does (rule 1): the
        #: gateway's ``Bases.driving_wheel``.
        self.driven_by = driven_by
        #: Held while a play, or a base's drive, takes its devices (rule 1).
        self.players = threading.Lock()
        self._lock = threading.Lock()
        self._running: dict[str, Running] = {}

    # -- commands (a worker thread: rule 5) ------------------------------------------------------

    def command(
        self, payload: bytes, came_under: int | None = None, limit: int = MAX_TRAJECTORY_PAYLOAD
    ) -> dict[str, Any]:
        """The reply to one query on the trajectory key; ``came_under``: the gateway's count
        of e-stops when the query came (a play is refused ``estopped`` past another);
        ``limit``: the largest payload taken (the key's; the ROS 2 face's own JSON may be
        larger than the message it came in)."""
        fields = decode_object(payload, limit=limit)
        request = TRAJECTORY_COMMAND_ADAPTER.validate_python(fields)
        if isinstance(request, TrajectoryPlay):
            return self.play(request, came_under)
        if isinstance(request, TrajectoryCancel):
            return self.cancel(request.id)
        with self._lock:
            running = [r.summary(time.time()) for r in self._running.values()]
        return ok_reply(trajectories=running)

    def play(self, request: TrajectoryPlay, came_under: int | None = None) -> dict[str, Any]:
        self._check_bases(request.devices)  # first, by name; again as the play is chosen
        members = members_of(self.api, request)
        start_at = start_at_of(request.start_at)
        check_buses(members)
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
        with self.players:
            self._check_bases(request.devices)
            with self._lock:
                if came_under is not None and came_under != self.api.estops:
                    raise cancelled_by_estop()  # sent before an e-stop (a reset may follow)
                self._check_id(request)
                taken = {m.name for m in members}
                for other in list(self._running.values()):
                    if other.id == request.id or taken & {m.name for m in other.members}:
                        self._end(other, "replaced", keep=frozenset(taken))
                self._running[request.id] = running
            for runner in {m.runner for m in members}:
                runner.play({m.name: m.sampler for m in members if m.runner is runner}, start_bus)
        self._event(running, "trajectory_started", start_at=start_at, end_at=running.end_at)
        return ok_reply(
            trajectory={
                "id": request.id,
                "start_at": start_at,
                "end_at": running.end_at,
                "devices": request.devices,
            }
        )

    def playing(self, device: str) -> str | None:
        """The id of the running trajectory ``device`` plays, if it plays one."""
        with self._lock:
            for running in self._running.values():
                if any(member.name == device for member in running.members):
                    return running.id
        return None

    def cancel(self, trajectory: str) -> dict[str, Any]:
        with self._lock:
            running = self._running.get(trajectory)
            if running is None:
                raise RefusedError("bad_command", f"no trajectory {trajectory!r} is running")
            self._end(running, "canceled")
        return ok_reply(canceled=trajectory)

    # -- watching (the loop's thread: rules 3 and 4) ---------------------------------------------

    @property
    def running(self) -> bool:
        """Whether a trajectory runs (``tick`` has work every round)."""
        return bool(self._running)

    def tick(self) -> None:
        """Feedback, aborts and results of every running trajectory, at this moment."""
        moment = time.time()
        with self._lock:
            for running in list(self._running.values()):
                ended = verdict(running, moment)
                if ended is not None:
                    self._end(running, *ended)
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

    def _check_bases(self, devices: list[str]) -> None:
        """A wheel a base drives is refused (rule 1); for good under ``players``."""
        for device in devices:
            if (base := self.driven_by(device)) is not None:
                raise RefusedError(
                    "busy",
                    f"{device} is a wheel of base {base}, which is driving it: stop the base "
                    "and wait until it is at rest (its status says driving false; a trajectory "
                    "would take one wheel from it)",
                )

    def _check_id(self, request: TrajectoryPlay) -> None:
        """A running trajectory's id is its client's (rule 1): under the lock."""
        other = self._running.get(request.id)
        if other is not None and other.client != request.client:
            raise RefusedError(
                "bad_command",
                f"trajectory id {request.id!r} is taken by a trajectory another client plays: "
                "choose another id",
            )

    def _feedback(self, running: Running, moment: float) -> dict[str, Any]:
        t_s = moment - running.start_at
        devices = []
        for member in running.members:
            desired = member.value(t_s)
            last = member.runner.plays.commanded(member.name)
            commanded = None if last is None else last[1]
            read = member.measured()
            measured = None if read is None else read[1]
            error = running.errors.get(member.name)
            devices.append(
                {
                    "device": member.name,
                    "desired": desired,
                    "commanded": commanded,
                    "measured": measured,
                    "error": error,
                    "joint": {  # the same in SI (rule 4)
                        "name": member.driver.joint.name,
                        "unit": member.si_unit,
                        "desired": member.si(desired),
                        "commanded": None if commanded is None else member.si(commanded),
                        "measured": None if measured is None else member.si(measured),
                        "error": None if error is None else member.si_difference(error),
                    },
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
                member.runner.stop_playing(member.name, speed=member.speed)
        outcome = {"result": result, "errors": running.errors} | (
            {"reason": reason} if reason else {}
        )
        self.publish(self._feedback_key(running), {"ts": time.time(), "id": running.id, **outcome})
        self._event(running, "trajectory_ended", **outcome)

    def _event(self, running: Running, type_: str, **fields: Any) -> None:
        client = {"client": running.client} if running.client else {}
        self.on_event(DeviceEvent("*", type_, {"id": running.id, **client, **fields}))

    def _feedback_key(self, running: Running) -> str:
        return f"{self.base}/trajectory/{running.id}/feedback"
