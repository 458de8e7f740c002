"""A ``play``'s checks: whether each device may play it, from where, and whether the buses
have the room, before anything moves.

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
   time than it has (``out_of_range``, naming the bus).
"""

from __future__ import annotations

import time
from typing import Any

from busgate.errors import BusgateError, RefusedError
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import Driver, Effect
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.bounds import value_refused
from busgate.gateway.trajectory.interpolation import paths_of
from busgate.gateway.trajectory.members import FIELDS, Gateway, Member
from busgate.schemas.trajectory import TrajectoryPlay

#: With no ``start_at``: how far ahead the trajectory starts (every bus takes it in by then).
LEAD_S = 0.1
#: A ``start_at`` nearer than this cannot be met by every bus: refused.
MIN_LEAD_S = 0.02
MAX_AHEAD_S = 3600.0
#: The share of a bus's time a trajectory's ticks may take, beside what it does already.
BUS_SHARE = 0.9


def members_of(gateway: Gateway, request: TrajectoryPlay) -> list[Member]:
    """The devices of ``request``, each with its path from where it is commanded, checked
    (rule 1): ``RefusedError`` (or the device's own refusal) for the first that may not play."""
    key, measured_key = FIELDS[request.values_field]
    paths = paths_of(request, [_start_value(gateway, d, key) for d in request.devices])
    members = []
    for index, (name, path) in enumerate(zip(request.devices, paths, strict=True)):
        runner, driver = device_of(gateway, name)
        _check_device(runner, driver, request.client, request.require_claim)
        member = Member(
            name,
            runner,
            driver,
            path,
            key,
            measured_key,
            _nth(request.path_tolerance, index),
            _nth(request.goal_tolerance, index),
            request.client is not None and holds(runner, name, request.client),
        )
        _check_path(member)
        members.append(member)
    return members


def device_of(gateway: Gateway, name: str) -> tuple[BusRunner, Driver]:
    found = gateway.devices.get(name)
    if found is None:
        raise RefusedError(
            "unknown_device",
            f"no device {name!r} on gateway {gateway.name}: a trajectory plays the "
            "devices of one gateway",
        )
    return found


def _check_device(
    runner: BusRunner, driver: Driver, client: str | None, require_claim: bool
) -> None:
    if not runner.owner.is_open:
        raise RefusedError("bus_unavailable", f"bus {runner.name} of {driver.name} is down")
    runner.authority.judge(driver.name, Effect.MOTION, client, require_claim=require_claim)
    if not driver.online:
        raise RefusedError("device_timeout", f"{driver.name} is offline: it does not answer")


def _start_value(gateway: Gateway, name: str, key: str) -> float:
    """Where ``name`` is commanded: its trajectory's last tick, while it plays, or once it
    left while nothing was read from it since; else its state's target, else its measured
    value (0 when nothing is known)."""
    runner, _ = device_of(gateway, name)
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


def start_at_of(start_at: float | None) -> float:
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


def check_buses(members: list[Member]) -> None:
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


def _nth(values: list[float] | None, index: int) -> float | None:
    return None if values is None else values[index]


def _read_after(state: dict[str, Any], moment: float) -> bool:
    """Whether ``state`` was read (its ``ts``, wall clock) after ``moment`` (bus clock)."""
    read = state.get("ts")
    return read is not None and now() - (time.time() - read) > moment


def holds(runner: BusRunner, device: str, client: str | None) -> bool:
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
