"""A ``play``'s checks: whether each device may play it, from where, and whether the buses
have the room, before anything moves.

Rules of this file:

1. A ``play`` is refused, with a stable code and nothing moving, when: the points are
   malformed (``bad_command``; too many: ``out_of_range``); a device is not on this gateway
   (``unknown_device``) or has no stream of the trajectory's values (``bad_command``); one is
   claimed by another client (``claimed``) or, with ``require_claim``, not by its client
   (``not_claimed``), e-stopped (``estopped``), offline
   (``device_timeout``) or on a bus that is down (``bus_unavailable``); its path would leave
   its joint's limits (rule 2) or a value of it is one its device refuses (``out_of_range``,
   or the device's own code); ``start_at`` is past, too close to now for the buses, or over
   an hour ahead (``out_of_range``); the ticks would need more of a bus's time than it has
   (``out_of_range``, naming the bus).
2. Every play, in raw or joint units, is held to each device's joint (``driver.joint``): a
   position path stays within its ``min`` and ``max`` (the path itself, unrounded, as a
   one-shot target is judged in SI before it is rounded), its velocity within
   ±``max_velocity`` and its acceleration within ±``max_acceleration`` when the joint has
   them; a speed path (rpm) stays within ±``max_velocity`` and its rate of change within
   ±``max_acceleration``. The whole path is bounded segment by segment
   (``trajectory.bounds``), so a cubic's overshoot between points is caught, at a cost that
   grows with the points, not with the ticks. A refusal is ``out_of_range`` naming the joint,
   the limit and the value in the joint's unit, and when the path reaches it.
3. A play in joint units has its points converted to each device's raw units before its path
   is built (``interpolation.path_of``), and its tolerances divided by the joint's scale:
   from there on everything is raw, and nothing is clamped into a limit it was past.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from busgate.errors import BusgateError, RefusedError
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import Driver, Effect
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.bounds import Refused, rate_refused, refusal
from busgate.gateway.trajectory.interpolation import path_of
from busgate.gateway.trajectory.members import Gateway, Member, Stream, stream_of
from busgate.schemas.joints import ON_THE_LIMIT, Joint
from busgate.schemas.trajectory import TrajectoryPlay
from busgate.schemas.validation import shown

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
    for name in request.devices:  # every device here before any other check
        device_of(gateway, name)
    members = []
    for index, name in enumerate(request.devices):
        runner, driver = device_of(gateway, name)
        _check_device(runner, driver, request.client, request.require_claim)
        stream = stream_of(driver, request.values_field)
        start = _start_value(runner, name, stream)
        joint = driver.joint
        per_raw = abs(joint.scale) if request.units == "joint" else 1.0  # rule 3
        member = Member(
            name,
            runner,
            driver,
            path_of(request, index, start, joint),
            stream,
            _raw(_nth(request.path_tolerance, index), per_raw),
            _raw(_nth(request.goal_tolerance, index), per_raw),
            request.client is not None and holds(runner, name, request.client),
        )
        check_path(member, start)
        members.append(member)
    return members


def device_of(gateway: Gateway, name: str) -> tuple[BusRunner, Driver]:
    found = gateway.devices.get(name)
    if found is None:
        raise RefusedError(
            "unknown_device",
            f"no device '{shown(name)}' on gateway {gateway.name}: a trajectory plays the "
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


def _start_value(runner: BusRunner, name: str, stream: Stream) -> float:
    """Where ``name`` is commanded: its trajectory's last tick, while it plays, or once it
    left while nothing was read from it since, as its follow stream's last tick once that
    ended when its state does not say that tick's target (``plays`` rule 4: an LA's); else
    its state's commanded value, else its measured value (0 when nothing is known)."""
    commanded = runner.plays.commanded(name)
    if commanded is not None:
        return float(commanded[1])
    state = runner.states.get(name) or {}
    held = runner.plays.held(name)
    if held is not None and not _read_after(state, held[0]):
        return float(held[1])  # the state was read before that tick: its target is older
    fields = [f for f in (stream.commanded, stream.measured) if f is not None]
    known = [float(state[f]) for f in fields if state.get(f) is not None]
    return known[0] if known else 0.0


def _to_the_ms(seconds: float, sign: str = "") -> str:
    """``seconds`` to the millisecond, or in powers of ten where that would be hundreds of
    digits (``-1e300`` is a float a client may send)."""
    return f"{seconds:{sign}.3f}" if abs(seconds) < 1e15 else f"{seconds:{sign}.6g}"


def start_at_of(start_at: float | None) -> float:
    moment = time.time()
    if start_at is None:
        return moment + LEAD_S
    if start_at < moment + MIN_LEAD_S:
        raise RefusedError(
            "out_of_range",
            f"start_at {_to_the_ms(start_at)} is {_to_the_ms(start_at - moment, '+')} s from "
            f"now: at least {MIN_LEAD_S * 1000:.0f} ms ahead, for every bus to meet it",
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


def _raw(tolerance: float | None, per_raw: float) -> float | None:
    """A tolerance in the play's units in raw units (``per_raw``: the play's units per raw)."""
    return None if tolerance is None else tolerance / per_raw


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


def check_path(member: Member, start: float) -> None:
    """The member's whole path from ``start`` (where its device is commanded) within its
    joint's limits and taken by its device (rule 2): ``RefusedError`` naming the first value
    past a limit, else the device's own refusal."""
    joint = member.driver.joint
    if member.speed:
        _check_speeds(member, joint)
    else:
        _check_positions(member, joint)
    _check_first_step(member, joint, start)


def _check_first_step(member: Member, joint: Joint, start: float) -> None:
    """A first point at ``t_s`` 0 replaces the start (``interpolation`` rule 2): the device is
    sent it at the first tick, a step no segment holds. With the joint's limit of that step
    (``max_velocity`` for a position, ``max_acceleration`` for a speed), it is held to it as
    a move over one follow period (``Joint.takes_step``)."""
    step = member.path.knots[0].value - start
    period = member.driver.follow_period_s
    if joint.takes_step(step, period, speed=member.speed):
        return
    at_start = Refused(member.path.knots[0].value, 0.0)
    if member.speed:
        raise _beyond(joint, "acceleration", joint.velocity_si(step / period),
                      f"{joint.unit}/s²", at_start, "max_acceleration",
                      joint.max_acceleration or 0.0, _FIRST_STEP)  # fmt: skip
    raise _beyond(joint, "velocity", step * joint.scale / period, f"{joint.unit}/s", at_start,
                  "max_velocity", joint.max_velocity or 0.0, _FIRST_STEP)  # fmt: skip


#: What a refusal of a first point's step says besides (``_check_first_step``).
_FIRST_STEP = (
    ": the first point, at t_s 0, is a step from where the joint is commanded, sent in one "
    "follow period (leave t_s 0 out to move there along the path)"
)


def _check_positions(member: Member, joint: Joint) -> None:
    """A position path against the joint's ``min`` and ``max`` (the path itself, in SI), its
    velocity against ``max_velocity`` and its acceleration against ``max_acceleration``
    (rule 2)."""

    def within(value: float) -> bool:
        try:
            joint.check_position_si(joint.position_si(value))
        except RefusedError:
            return False
        return True

    found = refusal(member.path, lambda value: within(value) and member.takes(value))
    if found is not None:
        if not within(found.value):
            si = joint.position_si(found.value)
            side, limit = ("min", joint.min) if si < joint.min else ("max", joint.max)
            raise _beyond(joint, "position", si, joint.unit, found, side, limit)
        _device_refuses(member, found)
    per_raw = abs(joint.scale)  # SI per raw unit: a raw rate's SI magnitude
    for order, what, unit, name in _RATES:
        limit = getattr(joint, name)
        rate = None if limit is None else rate_refused(
            member.path, order, _at_most(limit / per_raw))  # fmt: skip
        if rate is not None:
            raise _beyond(joint, what, rate.value * joint.scale, joint.unit + unit, rate, name,
                          limit)  # fmt: skip


#: A position path's rates held to a joint's limits: (the derivative's order, what it is,
#: its unit after the joint's, the joint's limit).
_RATES = ((1, "velocity", "/s", "max_velocity"), (2, "acceleration", "/s²", "max_acceleration"))


def _check_speeds(member: Member, joint: Joint) -> None:
    """A speed path (the family's speed unit, rpm) against ``max_velocity``, its rate of change
    against ``max_acceleration`` (rule 2)."""
    top = math.inf if joint.max_velocity is None else abs(joint.speed_of(joint.max_velocity))
    within = _at_most(top)
    found = refusal(member.path, lambda speed: within(speed) and member.takes(speed))
    if found is not None:
        if not within(found.value):
            assert joint.max_velocity is not None  # else every speed is within
            raise _beyond(joint, "velocity", joint.velocity_si(found.value), f"{joint.unit}/s",
                          found, "max_velocity", joint.max_velocity)  # fmt: skip
        _device_refuses(member, found)
    if joint.max_acceleration is not None:
        rate = rate_refused(member.path, 1, _at_most(abs(joint.speed_of(joint.max_acceleration))))
        if rate is not None:
            raise _beyond(joint, "acceleration", joint.velocity_si(rate.value),
                          f"{joint.unit}/s²", rate, "max_acceleration",
                          joint.max_acceleration)  # fmt: skip


def _at_most(limit: float) -> Callable[[float], bool]:
    """Whether a value's magnitude is within ``limit`` (on it counts as within, as in a
    joint's own checks: ``ON_THE_LIMIT``)."""
    top = limit * (1 + ON_THE_LIMIT)
    return lambda value: abs(value) <= top


def _device_refuses(member: Member, found: Refused) -> None:
    """The device's own refusal of a value its path reaches (it raises, saying why)."""
    member.driver.follow_target(member.payload(found.value))
    raise RefusedError(  # not reached: ``takes`` said the device refuses it
        "out_of_range", f"{member.name} refuses {found.value:g} at t={found.t_s:g} s"
    )


def _beyond(
    joint: Joint, what: str, value: float, unit: str, found: Refused, limit_name: str,
    limit: float, why: str = "",
) -> RefusedError:  # fmt: skip
    """The refusal of a path past one of ``joint``'s limits (rule 2), in SI."""
    return RefusedError(
        "out_of_range",
        f"joint {joint.name}: {what} {value:g} {unit} at t={found.t_s:g} s is beyond its "
        f"{limit_name} {limit:g} {unit}{why}",
    )
