"""``[[bases]]`` in the config: two ZLAC706 hub motors driven as one differential drive.

Rules of this file:

1. A base names two devices of the gateway, ``left`` and ``right``, each a ZLAC706 whose
   joint is a velocity joint in radians (a joint table with ``unit = "rad"``): the base's
   kinematics speak metres and radians, and a wheel's direction is its joint's (a negative
   ``scale`` turns one side round). A device is in one base at most.
2. Every limit must be one the wheels can reach: ``max_linear_mps`` straight ahead, and
   ``max_angular_radps`` turning on the spot, each within the wheels' ``max_velocity`` (or
   their top speed); a base that promises what its wheels cannot do is refused, naming both.
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
    wheel_radius_m: Positive
    track_m: Positive
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

    def wheel_speed_needed(self) -> tuple[float, float]:
        """The wheel speeds (rad/s) the limits ask: straight ahead at ``max_linear_mps``, and
        turning on the spot at ``max_angular_radps`` (rule 2)."""
        straight = self.max_linear_mps / self.wheel_radius_m
        spin = self.max_angular_radps * self.track_m / 2 / self.wheel_radius_m
        return straight, spin


def reachable_radps(joint: Joint) -> float:
    """The fastest a wheel may turn, rad/s: its joint's ``max_velocity``, else its top speed."""
    top = joint.declaration.top_speed
    reachable = abs(joint.velocity_si(top)) if top is not None else math.inf
    return reachable if joint.max_velocity is None else min(reachable, joint.max_velocity)


def wheel_problem(base: BaseConfig, side: str, reachable_radps: float) -> str | None:
    """Why a wheel that turns at most ``reachable_radps`` cannot serve ``base`` (rule 2)."""
    straight, spin = base.wheel_speed_needed()
    wheel = getattr(base, side)
    if straight > reachable_radps * (1 + 1e-9):
        return (
            f"max_linear_mps {base.max_linear_mps:g} needs the wheels at {straight:.4g} rad/s "
            f"({base.max_linear_mps:g} / wheel_radius_m {base.wheel_radius_m:g}), but {side} "
            f"wheel {wheel!r} turns at most {reachable_radps:.4g} rad/s"
        )
    if spin > reachable_radps * (1 + 1e-9):
        return (
            f"max_angular_radps {base.max_angular_radps:g} needs the wheels at {spin:.4g} rad/s "
            f"(× track_m / 2 / wheel_radius_m), but {side} wheel {wheel!r} turns at most "
            f"{reachable_radps:.4g} rad/s"
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
