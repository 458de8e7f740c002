"""``[[bases]]`` in the config: two ZLAC706 hub motors driven as one differential drive.

Rules of this file:

1. A base names two devices of the gateway, ``left`` and ``right``, each a ZLAC706 whose
   joint is a velocity joint in radians (a joint table with ``unit = "rad"``): the base's
   kinematics speak metres and radians, and a wheel's direction is its joint's (a negative
   ``scale`` turns one side round). A device is in one base at most.
2. Every limit must be one the wheels can reach: ``max_linear_mps`` straight ahead, and
   ``max_angular_radps`` turning on the spot, each within the wheels' ``max_velocity`` (or
   their top speed), and ``max_linear_accel`` and ``max_angular_accel`` so, each within the
   wheels' ``max_acceleration``; a base that promises what its wheels cannot do is refused,
   naming both. (Both at once may ask a wheel more: the drive holds each wheel within its
   own limits as it goes, ``kinematics`` rules 2 and 3.)
3. Checked with the rest of the config (``schemas.config``), before any port is opened.
4. What the base's keys take (below) is validated as every command is: strict, closed,
   finite; a twist beyond the base's limits is not refused but scaled down (``kinematics``).
5. What a base publishes (``Odometry``, last) is closed as every published message is: a
   client reads it with this model (``busgate.client``).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from busgate.schemas.base import (
    MAX_CLAIM_S,
    ClientId,
    CommandModel,
    FollowSeq,
    Name,
    Published,
)
from busgate.schemas.joints import Joint

#: A base's name, as every name (``<p>/<gw>/base/<name>/cmd``).
BaseName = Name
Positive = Annotated[float, Field(gt=0, le=1e6)]
#: A wheel's radius or the track between the wheels, m: a millimetre at least (a track of
#: 1e-300 m passed, and the odometry's turn, divided by it, overflows), 100 m at most.
Length = Annotated[float, Field(ge=0.001, le=100.0)]
#: The longest a twist without a new one may drive the base (``cmd_timeout_s``) and the
#: longest ``duration_s`` a twist may ask.
MAX_HOLD_S = 10.0


class BaseConfig(BaseModel):
    """One differential-drive base (the rules above)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    name: BaseName
    kind: Literal["diff_drive"] = "diff_drive"
    left: str
    right: str
    wheel_radius_m: Length
    track_m: Length
    max_linear_mps: Positive
    max_angular_radps: Positive
    max_linear_accel: Positive
    max_angular_accel: Positive
    cmd_timeout_s: Annotated[float, Field(gt=0, le=MAX_HOLD_S)] = 0.5

    @model_validator(mode="after")
    def _two_wheels(self) -> BaseConfig:
        if self.left == self.right:
            raise ValueError(f"left and right are both {self.left!r}: a base has two wheels")
        return self

    def wheel_needs(self, linear: float, angular: float) -> tuple[float, float]:
        """What a wheel is asked, straight ahead at ``linear`` and turning on the spot at
        ``angular`` (speeds in m/s and rad/s give rad/s; accelerations, rad/s²: rule 2)."""
        return linear / self.wheel_radius_m, angular * self.track_m / 2 / self.wheel_radius_m


def top_radps(joint: Joint) -> float:
    """The fastest a wheel's drive turns it, rad/s: its top speed (``inf`` when not known)."""
    top = joint.declaration.top_speed
    return abs(joint.velocity_si(top)) if top is not None else math.inf


def reachable_radps(joint: Joint) -> float:
    """The fastest a wheel may turn, rad/s: its joint's ``max_velocity``, else its top speed."""
    reachable = top_radps(joint)
    return reachable if joint.max_velocity is None else min(reachable, joint.max_velocity)


def reachable_radps2(joint: Joint) -> float:
    """How fast a wheel's speed may change, rad/s²: its joint's ``max_acceleration``."""
    return math.inf if joint.max_acceleration is None else joint.max_acceleration


def wheel_problem(base: BaseConfig, side: str, joint: Joint) -> str | None:
    """Why the wheel ``side`` of ``base``, ``joint``, cannot serve it (rule 2)."""
    speed, accel = reachable_radps(joint), reachable_radps2(joint)
    straight, spin = base.wheel_needs(base.max_linear_mps, base.max_angular_radps)
    straight_accel, spin_accel = base.wheel_needs(base.max_linear_accel, base.max_angular_accel)
    radius = f"/ wheel_radius_m {base.wheel_radius_m:g}"
    on_the_spot = "× track_m / 2 / wheel_radius_m"
    needs = (  # (key, its limit, how the wheel's need follows, the need, what it has, unit)
        ("max_linear_mps", base.max_linear_mps, radius, straight, speed, "rad/s"),
        ("max_angular_radps", base.max_angular_radps, on_the_spot, spin, speed, "rad/s"),
        ("max_linear_accel", base.max_linear_accel, radius, straight_accel, accel, "rad/s²"),
        ("max_angular_accel", base.max_angular_accel, on_the_spot, spin_accel, accel, "rad/s²"),
    )
    for key, limit, how, needed, reachable, unit in needs:
        if needed > reachable * (1 + 1e-9):
            return (
                f"{key} {limit:g} needs the wheels at {needed:.4g} {unit} ({limit:g} {how}), "
                f"but {side} wheel {getattr(base, side)!r} reaches at most {reachable:.4g} {unit}"
            )
    return None


# -- what the base's keys take ---------------------------------------------------------------
#: The fastest a twist may ask, in m/s and rad/s, before the base's own limits (which then
#: scale it down: a finite number the arithmetic cannot overflow on).
MAX_TWIST = 1e3
TwistValue = Annotated[float, Field(ge=-MAX_TWIST, le=MAX_TWIST)]


class TwistCommand(CommandModel):
    """Drive at ``linear`` m/s and ``angular`` rad/s (counter-clockwise positive), scaled down
    to the base's limits keeping the curvature, for ``cmd_timeout_s`` (or ``duration_s``, at
    most ``MAX_HOLD_S``), then ramped to 0."""

    op: Literal["twist"]
    linear: TwistValue = 0.0
    angular: TwistValue = 0.0
    duration_s: Annotated[float, Field(gt=0, le=MAX_HOLD_S)] | None = None


class TwistTarget(CommandModel):
    """One target of the base's twist stream (``<p>/<gw>/base/<name>/twist``). ``seq``, the
    client's count of what it sends the stream, orders a target against a ``stop`` whichever
    of zenoh's threads brought each (as a follow stream's against its ``end_follow``)."""

    linear: TwistValue = 0.0
    angular: TwistValue = 0.0
    seq: FollowSeq | None = None


class BaseStop(CommandModel):
    """Ramp to 0 at the deceleration limits now; with ``seq``, the client's twists numbered
    at or below it are dropped however late they come (one with the stop's own ``seq``:
    numbered alike, it cannot be ordered)."""

    op: Literal["stop"]
    seq: FollowSeq | None = None


class BaseClaim(CommandModel):
    """Both wheels for ``client``, at once (or neither)."""

    op: Literal["claim"]
    client: ClientId
    ttl_s: Annotated[float, Field(gt=0, le=MAX_CLAIM_S)] = 60.0


class BaseRelease(CommandModel):
    op: Literal["release"]
    client: ClientId


class BasePower(CommandModel):
    """Both power stages on (velocity mode first) or off."""

    op: Literal["enable", "disable"]


class ResetOdometry(CommandModel):
    """The pose back to (0, 0, 0) from the wheels' next reading."""

    op: Literal["reset_odometry"]


class BaseStatus(CommandModel):
    op: Literal["status"]


BaseCommand = Annotated[
    TwistCommand | BaseStop | BaseClaim | BaseRelease | BasePower | ResetOdometry | BaseStatus,
    Field(discriminator="op"),
]
BASE_COMMAND_ADAPTER: TypeAdapter[BaseCommand] = TypeAdapter(BaseCommand)


# -- what the base publishes -------------------------------------------------------------------


class CommandedTwist(Published):
    linear: float
    angular: float


class Odometry(Published):
    """What ``<p>/<gw>/base/<name>/odom`` carries, whenever both wheels were read again: the
    pose integrated from the wheels' encoders since the gateway started or the last
    ``reset_odometry`` (``x``, ``y`` in metres, ``theta`` in radians, counter-clockwise
    positive), the twist measured over the last step (``linear`` m/s, ``angular`` rad/s), and
    ``ts``, the wall-clock time of the readings it was taken at (as telemetry's ``ts``); and
    ``commanded``, the twist the wheels were last sent (``linear``, ``angular``: beside the
    measured one, what a dashboard shows)."""

    base: BaseName
    ts: float
    x: float
    y: float
    theta: float
    linear: float
    angular: float
    commanded: CommandedTwist
