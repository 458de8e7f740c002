"""When a running trajectory is over, and how: its verdict at a moment, from what its devices
and their buses say.

Rules of this file:

3. Watched on the loop's thread (``tick``), a running trajectory ends ``succeeded`` once every
   device has been sent its last point's value (the first tick at or after it) and is within
   its goal tolerance (at once without one), else is ``aborted`` (each device holding, a speed
   ramped to 0) on: an e-stop, a device offline, a device whose bus thread (or bus worker)
   has been silent for ``SILENT_S`` (the other buses' devices would go on along a path this
   one no longer follows: a hung worker went unnoticed for 4 s, until it was killed), its
   client gone, a claim it played under
   lost, a device claimed by another client, a device its bus took out of it (it could no
   longer take its target, or every device was stopped: ``Plays.refusal``), a measured value
   off the path by more than its path tolerance (compared with the path at the moment the
   value was read), or no goal by ``goal_time_s`` after the last point. All but the
   tolerances are watched from the moment it is accepted, before its start too. ``cancel``
   ends it ``canceled`` the same way.
"""

from __future__ import annotations

from busgate.errors import BusgateError
from busgate.gateway.drivers.base import Effect
from busgate.gateway.scheduler.plays import ESTOPPED
from busgate.gateway.trajectory.checks import holds
from busgate.gateway.trajectory.members import Member, Running

#: How long past its last point (and ``goal_time_s``) a trajectory waits for the tick that
#: sends each device that point's value (the next slot, a period at most) before it is
#: aborted: a bus that stopped ticking without any other reason to abort.
LAST_TICK_WAIT_S = 1.0
#: How long a member's bus thread, or its bus worker, may go without turning its loop or
#: saying a word (every 50 and 100 ms while well) before the trajectory is aborted (rule 3).
SILENT_S = 0.5


def verdict(running: Running, moment: float) -> tuple[str, ...] | None:
    """``(result, reason)`` once ``running`` is over, else ``None`` (rule 3)."""
    for member in running.members:
        driver = member.driver
        if driver.estopped:
            return ("aborted", "estop")
        if not driver.online:
            return ("aborted", f"{member.name} offline")
        if not member.runner.keeping_schedule(SILENT_S):
            return ("aborted", f"{member.name}'s bus silent for {SILENT_S:g} s")
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
    errors = errors_of(running)
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


def errors_of(running: Running) -> dict[str, float | None]:
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


def _within(error: float | None, tolerance: float | None) -> bool:
    """No tolerance, or a known error within it."""
    return tolerance is None or (error is not None and abs(error) <= tolerance)


def _sent_last(member: Member) -> bool:
    """Whether ``member``'s bus has sent it its last point's value (a tick at or after it)."""
    commanded = member.runner.plays.commanded(member.name)
    return commanded is not None and commanded[0] >= member.path.end_s


def _claim_problem(member: Member, client: str | None) -> str | None:
    """Why ``client``'s trajectory may no longer move ``member``: the claim it played under
    lapsed or went, or another client claimed the device; ``None`` when it may."""
    runner, device = member.runner, member.name
    if member.claimed and not holds(runner, device, client):
        return f"claim on {device} lost"
    try:
        runner.authority.judge(device, Effect.SETTING, client)  # the claim (an e-stop: above)
    except BusgateError as exc:
        return str(exc)
    return None
