"""Joints: every configured device as one joint in SI units, with its calibration and limits.

A family says once, in its schema module (``JOINT``, a ``JointDeclaration``), which of its raw
telemetry fields are the joint's position, velocity and effort, what a raw unit of each is,
and which of its commands and follow payloads set a position or a speed. The config's
``[buses.devices.joint]`` table (``JointTable``) gives a device its joint's name, unit,
calibration and limits. ``Joint`` is the two together: the pure conversions and checks that
every path uses. Generic code reads these and names no family field.

Rules of this file:

1. Calibration is linear: ``si = offset + scale × raw`` for a position; a velocity or an
   acceleration scales by ``scale`` alone. A speed the family counts in turns per minute
   (``rpm``) is ``raw_per_turn / 60`` raw position units per second.
2. Limits are SI. A position joint's limits in raw units are the whole counts inside them and
   inside the device's range (``raw_limits``), so a target rounded from SI never crosses one.
3. Without a table a device is a joint in raw units (``unit = "raw"``, scale 1) whose limits
   are the device's own range, so the joint vocabulary works on every device.
4. A refusal is ``out_of_range`` and names the joint, the limit and the value, in the joint's
   unit; nothing here sends anything.
5. What clients read (``Joint.state``) is rounded to ``PUBLISHED_DIGITS`` significant digits,
   the most a double keeps through a decimal: without the float noise of ``offset + scale ×
   raw`` in the last digits (1500 × 5e-6 m computes as 0.007500000000000001; it is published
   0.0075), and with every count a double can tell apart.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

from busgate.errors import RefusedError
from busgate.schemas.base import FINITE, Name, Published
from busgate.schemas.families import FAMILIES

JointType = Literal["position", "velocity"]
JOINT_TYPES: tuple[JointType, ...] = get_args(JointType)
#: What a command or a follow target sets: a position (raw units), a speed (the family's
#: speed unit: rpm or raw units per second) or an effort (the family's effort unit).
Quantity = Literal["position", "velocity", "effort"]
#: A limit is refused past this (as the trajectory schema's values: past it is a typo).
MAX_SI = 1e9
#: The smallest |scale| a table may give: below it an SI value of MAX_SI is no float of raw.
MIN_SCALE = 1e-12
#: How far past a limit a value still counts as on it (floating-point noise, relative)...
ON_THE_LIMIT = 1e-9
#: ... and never more than this part of one count of the device: relative alone, a limit
#: near a large offset took values a count or more past it (an audit: 0.09 m past an LA's
#: stroke at an offset of 1e8 m; a raw count past max at 1.5e9 counts).
COUNT_SLACK = 1e-3
#: Significant digits of a joint's published values (rule 5).
PUBLISHED_DIGITS = 15
#: A unit as a joint is published with: ``m``, ``rad`` or ``raw``, an effort's ``N`` or
#: ``A``; bounded, with room for units to come, so that a peer's is never megabytes.
UNIT_CHARS = 16
Unit = Annotated[str, Field(max_length=UNIT_CHARS)]
#: The longest joint name a gateway gives (a name, as every name of its config).
JOINT_NAME_CHARS = 64


def finite_or_none(value: Any) -> float | None:
    """``value`` when it is a finite number (not a bool), else ``None``: a joint's value as a
    display takes it from a peer's message."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return value if math.isfinite(value) else None


def published(value: float) -> float:
    """``value`` to ``PUBLISHED_DIGITS`` significant digits (rule 5); 0 and a value that is
    not finite as they are."""
    if value == 0 or not math.isfinite(value):
        return value
    return round(value, PUBLISHED_DIGITS - 1 - math.floor(math.log10(abs(value))))


@dataclass(frozen=True, slots=True)
class JointDeclaration:
    """What a family's raw fields mean as a joint; each family's schema module has one
    (``JOINT``). Field names are the family's telemetry fields, in raw units."""

    #: The position targets the device takes, raw (its target register's range).
    raw_range: tuple[int, int]
    #: Telemetry fields of the measured position and of the commanded position target.
    position: str
    target: str
    #: The command that sets a position target, as ``(op, field)``; the follow payload's field
    #: of a position joint.
    move: tuple[str, str]
    follow_position: str | None = None
    #: The joint types the family can be; the first is a device's when its table names none.
    types: tuple[JointType, ...] = ("position",)
    #: The speed the family measures and commands, in rpm (``None``: not measured).
    speed_rpm: str | None = None
    target_speed_rpm: str | None = None
    #: The command that sets a speed (velocity joints), as ``(op, field)``, and the follow
    #: payload's field of a velocity joint.
    turn: tuple[str, str] | None = None
    follow_velocity: str | None = None
    #: Raw position units in one turn of the shaft, by the manual (``None``: not a rotary
    #: device); a table's ``raw_per_turn`` overrides it.
    raw_per_turn: float | None = None
    #: The effort the family measures: its field, its SI unit and the unit per raw count.
    effort: str | None = None
    effort_unit: str | None = None
    effort_per_raw: float = 1.0
    #: Whether a command sets an effort the gateway can bound (``max_effort``).
    effort_limited: bool = False
    #: The fastest speed the device takes, in its speed unit (``None``: no speed commands).
    top_speed: float | None = None

    def type_of(self, table: JointTable | None) -> JointType:
        """The type of a device of the family with ``table``: the table's, else the first."""
        return table.type if table is not None and table.type is not None else self.types[0]

    def raw_fields(self, joint_type: JointType) -> tuple[str, str]:
        """The telemetry fields of a joint's value, measured and commanded, raw: a velocity
        joint's speed when the family measures one, else its position."""
        if joint_type == "velocity" and self.speed_rpm is not None:
            return self.speed_rpm, self.target_speed_rpm or self.speed_rpm
        return self.position, self.target

    @property
    def follows(self) -> Literal["position", "velocity"] | None:
        """What the family's follow stream carries for a joint of its first type: positions,
        speeds, or nothing."""
        return self.follows_of(self.types[0])

    def follows_of(self, joint_type: JointType) -> Literal["position", "velocity"] | None:
        """What a joint of ``joint_type`` follows (SI targets): positions or speeds as its
        type says where the family's stream carries both (a ZLAC706's, by its mode), else
        what the stream carries; ``None``: the family has no stream."""
        if self.follow_position is not None and self.follow_velocity is not None:
            return joint_type
        if self.follow_position is not None:
            return "position"
        return "velocity" if self.follow_velocity is not None else None


def type_told(kind: str, joint: Any) -> JointType:
    """The type a state's ``joint`` (distrusted) says, else the one a device of ``kind`` has
    when its config names none (a state of a gateway of an earlier release)."""
    told = joint.get("type") if isinstance(joint, dict) else None
    declaration = declaration_of(kind)
    default: JointType = "position" if declaration is None else declaration.types[0]
    return next((known for known in JOINT_TYPES if known == told), default)


def declaration_of(kind: str) -> JointDeclaration | None:
    """The joint declaration of the family of ``kind`` (``None``: no such kind, or a family
    without one), for what reads a device's state by its kind."""
    family = FAMILIES.get(kind)
    return None if family is None else getattr(family.schema, "JOINT", None)


class JointTable(BaseModel):
    """A device's ``[buses.devices.joint]`` table (docs/joints.md)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    name: Name | None = None
    type: JointType | None = None
    unit: Literal["m", "rad"]
    scale: Annotated[float, Field(ge=-MAX_SI, le=MAX_SI)]
    offset: Annotated[float, Field(ge=-MAX_SI, le=MAX_SI)] = 0.0
    min: Annotated[float, Field(ge=-MAX_SI, le=MAX_SI)] | None = None
    max: Annotated[float, Field(ge=-MAX_SI, le=MAX_SI)] | None = None
    max_velocity: Annotated[float, Field(gt=0, le=MAX_SI)] | None = None
    max_acceleration: Annotated[float, Field(gt=0, le=MAX_SI)] | None = None
    max_effort: Annotated[float, Field(gt=0, le=MAX_SI)] | None = None
    raw_per_turn: Annotated[float, Field(gt=0, le=MAX_SI)] | None = None


class JointState(Published):
    """A joint's values in SI, from the same reading as the rest of its device's state
    (``null`` where the family cannot know)."""

    model_config = FINITE

    name: Name = Field(description="The joint's name (its table's, else the device's).")
    type: JointType = Field(description="A position joint, or a velocity joint.")
    unit: Unit = Field(description='Position unit: "m", "rad", or "raw" without a table.')
    position: float | None = Field(description="Position, in unit.")
    velocity: float | None = Field(description="Velocity, in unit per second.")
    effort: float | None = Field(description="Effort, in the joint's effort unit (info).")
    target: float | None = Field(
        description="What the joint is commanded to: a position joint's position, in unit; "
        "a velocity joint's velocity, in unit per second."
    )


def table_problems(declaration: JointDeclaration, table: JointTable) -> list[tuple[str, str]]:
    """``(key, what is wrong)`` for each key of ``table`` that ``declaration``'s family cannot
    take (``check-config`` and the config's validation refuse them)."""
    problems = []
    if abs(table.scale) < MIN_SCALE:
        problems.append(
            (
                "scale",
                f"must be at least {MIN_SCALE:g} in size (SI per raw unit; not 0; negative "
                "flips the direction)",
            )
        )
    if table.type is not None and table.type not in declaration.types:
        problems.append(("type", f"must be one of {', '.join(declaration.types)}"))
    if table.min is not None and table.max is not None and table.min >= table.max:
        problems.append(("min", f"{table.min:g} must be below max {table.max:g}"))
    if table.raw_per_turn is not None and declaration.raw_per_turn is None:
        problems.append(("raw_per_turn", "this kind is not a rotary device"))
    if declaration.type_of(table) == "velocity":
        problems += [
            (
                key,
                "bounds positions, and a velocity joint turns on without end: give the "
                'joint type = "position", or leave min and max out',
            )
            for key in ("min", "max")
            if getattr(table, key) is not None
        ]
    if problems:
        return problems
    low, high = sorted(table.offset + table.scale * raw for raw in declaration.raw_range)
    count, farthest = abs(table.scale), max(abs(low), abs(high))
    step = math.ulp(farthest)
    if step > COUNT_SLACK * count:
        return [
            (
                "offset",
                f"{table.offset:g} {table.unit} leaves no count of {count:g} {table.unit} told "
                f"apart near {farthest:g} {table.unit} (a double's step there is {step:g}): "
                "an offset nearer 0, or a larger scale",
            )
        ]
    lowest, highest = low - _slack(low, count), high + _slack(high, count)
    for key in ("min", "max"):
        value = getattr(table, key)
        if value is not None and not lowest <= value <= highest:
            problems.append(
                (key, f"{value:g} {table.unit} is outside the device's range {low:g}–{high:g}")
            )
    if problems or (table.min is None and table.max is None):
        return problems
    si_low = low if table.min is None else table.min
    si_high = high if table.max is None else table.max
    raw_ends = ((si_low - table.offset) / table.scale, (si_high - table.offset) / table.scale)
    first, last = whole_counts(raw_ends, declaration.raw_range)
    if first > last:  # a target would be rounded outside them (rule 2)
        problems.append(
            (
                "min",
                f"{si_low:g}–{si_high:g} {table.unit} holds no whole count of the device (one "
                f"count is {abs(table.scale):g} {table.unit}): widen the limits",
            )
        )
    return problems


def table_warnings(declaration: JointDeclaration, table: JointTable) -> list[tuple[str, str]]:
    """``(key, why it is ignored)`` for each key of ``table`` its family takes but cannot act
    on: ``max_effort`` where no command sets an effort (``check-config`` and ``busgate run``
    warn of it; the joint goes without it, so ``info`` shows no limit that is not kept)."""
    if table.max_effort is not None and not declaration.effort_limited:
        unit = f" {declaration.effort_unit}" if declaration.effort_unit else ""
        return [
            (
                "max_effort",
                f"{table.max_effort:g}{unit} is ignored: no command of this kind "
                "sets an effort, so there is none to bound (docs/joints.md)",
            )
        ]
    return []


def _slack(value: float, count: float = 1.0) -> float:
    """How far past ``value`` still counts as on it, where one count is ``count``."""
    return min(ON_THE_LIMIT * max(1.0, abs(value)), COUNT_SLACK * count)


def whole_counts(raw_ends: tuple[float, float], raw_range: tuple[int, int]) -> tuple[int, int]:
    """The first and last whole raw counts between two raw positions (in either order) and
    within ``raw_range``; the first past the last when there is none."""
    low, high = sorted(raw_ends)
    return (
        max(math.ceil(low - _slack(low)), raw_range[0]),
        min(math.floor(high + _slack(high)), raw_range[1]),
    )


@dataclass(frozen=True, slots=True)
class Joint:
    """One device as a joint: the conversions between its raw units and SI, and its limits."""

    name: str
    type: JointType
    unit: str
    scale: float
    offset: float
    min: float
    max: float
    max_velocity: float | None
    max_acceleration: float | None
    max_effort: float | None
    raw_per_turn: float | None
    declaration: JointDeclaration
    #: A table configured it (else: raw units, the device's range).
    configured: bool
    #: Raw position units per second in one unit of the family's speed (rule 1), and the
    #: telemetry field of the joint's commanded value: from the fields above, once.
    _raw_per_speed: float = field(init=False, repr=False, compare=False)
    _target_field: str = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        per_speed = 1.0  # a speed in raw units per second
        if self.declaration.speed_rpm is not None and self.raw_per_turn is not None:
            per_speed = self.raw_per_turn / 60.0  # a speed in rpm
        object.__setattr__(self, "_raw_per_speed", per_speed)
        object.__setattr__(self, "_target_field", self.declaration.raw_fields(self.type)[1])

    @classmethod
    def of(cls, device: str, declaration: JointDeclaration, table: JointTable | None) -> Joint:
        """The joint of ``device``: its table's, or the raw joint (rule 3)."""
        low, high = declaration.raw_range
        if table is None:
            return cls(device, declaration.type_of(None), "raw", 1.0, 0.0, low, high, None, None,
                       None, declaration.raw_per_turn, declaration, False)  # fmt: skip
        ends = sorted(table.offset + table.scale * raw for raw in (low, high))
        joint_type = declaration.type_of(table)
        return cls(
            table.name or device,
            joint_type,
            table.unit,
            table.scale,
            table.offset,
            ends[0] if table.min is None else table.min,
            ends[1] if table.max is None else table.max,
            table.max_velocity,
            table.max_acceleration,
            table.max_effort if declaration.effort_limited else None,
            table.raw_per_turn or declaration.raw_per_turn,
            declaration,
            True,
        )

    # -- positions ------------------------------------------------------------------------------

    def position_si(self, raw: float) -> float:
        return self.offset + self.scale * raw

    def position_raw(self, si: float) -> float:
        """The raw position of ``si``, unrounded."""
        return (si - self.offset) / self.scale

    @property
    def raw_limits(self) -> tuple[int, int]:
        """The whole raw positions inside the limits and the device's range (rule 2)."""
        ends = (self.position_raw(self.min), self.position_raw(self.max))
        return whole_counts(ends, self.declaration.raw_range)

    @property
    def limited(self) -> bool:
        """Whether the position limits are narrower than the device's own range."""
        return self.raw_limits != self.declaration.raw_range

    def target_raw(self, si: float) -> int:
        """The raw target of the SI position ``si``: refused beyond a limit, else rounded to
        the nearest whole count inside the limits."""
        self.check_position_si(si)
        low, high = self.raw_limits
        return min(max(round(self.position_raw(si)), low), high)

    def check_position_si(self, si: float) -> None:
        count = abs(self.scale)
        if not self.min - _slack(self.min, count) <= si <= self.max + _slack(self.max, count):
            limit, side = (self.min, "min") if si < self.min else (self.max, "max")
            raise self._refusal("position", si, self.unit, side, limit)

    def check_position(self, raw: float | None) -> None:
        """Refuse a raw position target outside the limits; ``None`` (a target the gateway
        cannot know, as a stored preset) is refused when the joint is limited."""
        if raw is None:
            if self.limited:
                raise RefusedError(
                    "out_of_range",
                    f"joint {self.name}: the command moves to a position the gateway cannot "
                    f"know, so it cannot keep the joint within {self._range()}",
                )
            return
        low, high = self.raw_limits
        if not low <= raw <= high:
            self.check_position_si(self.position_si(raw))
            # Inside in SI yet outside the whole counts: the nearest count is past the limit.
            side, limit = ("min", self.min) if raw < low else ("max", self.max)
            raise self._refusal("position", self.position_si(raw), self.unit, side, limit)

    # -- speeds and efforts --------------------------------------------------------------------

    def velocity_si(self, speed: float) -> float:
        """SI velocity of a speed in the family's unit (rpm when it declares one, else raw
        units per second)."""
        return self.scale * speed * self._raw_per_speed

    def speed_of(self, velocity: float) -> float:
        """The family's speed for the SI ``velocity`` (inverse of ``velocity_si``)."""
        return velocity / (self.scale * self._raw_per_speed)

    def check_velocity(self, speed: float | None) -> None:
        """Refuse a speed (the family's unit) past ``max_velocity``; ``None`` (a speed the
        gateway cannot know, as a ZLAC706's move at a top speed never set) is refused when
        the joint has one."""
        if self.max_velocity is None:
            return
        if speed is None:
            raise RefusedError(
                "out_of_range",
                f"joint {self.name}: the command moves at a speed the gateway cannot know (a "
                "top speed not set), so it cannot keep the joint within its max_velocity "
                f"{self.max_velocity:g} {self.unit}/s",
            )
        velocity = self.velocity_si(speed)
        if abs(velocity) > self.max_velocity * (1 + ON_THE_LIMIT):
            raise self._refusal(
                "velocity", velocity, f"{self.unit}/s", "max_velocity", self.max_velocity
            )

    def takes_step(self, step: float, period_s: float, *, speed: bool) -> bool:
        """Whether a step of ``step`` in one follow period (a trajectory's first tick, from
        where the joint was commanded) is within its limits: ``max_velocity`` for a position
        (raw; what is sent is rounded, half a count either way), ``max_acceleration`` for a
        speed (the family's unit); any step without that limit."""
        if speed:
            limit = self.max_acceleration
            top = None if limit is None else abs(self.speed_of(limit)) * period_s
            size = abs(step)
        else:
            limit = self.max_velocity
            top = None if limit is None else limit / abs(self.scale) * period_s
            size = max(0.0, abs(step) - 0.5)
        return top is None or size <= top * (1 + ON_THE_LIMIT)

    def check_effort(self, effort: float) -> None:
        """Refuse an effort (the family's effort unit) past ``max_effort``."""
        if self.max_effort is not None and abs(effort) > self.max_effort * (1 + ON_THE_LIMIT):
            unit = self.declaration.effort_unit or ""
            raise self._refusal("effort", effort, unit, "max_effort", self.max_effort)

    def check(self, quantity: Quantity, value: float | None) -> None:
        """Refuse what sets ``quantity`` to ``value`` beyond a limit (rule 4)."""
        if quantity == "position":
            self.check_position(value)
        elif quantity == "velocity":
            self.check_velocity(value)
        elif value is not None:
            self.check_effort(value)

    # -- commands in SI -----------------------------------------------------------------------

    def move_command(self, position: float) -> dict[str, Any]:
        """The kind's own command that moves a position joint to ``position`` (SI)."""
        if self.type != "position":
            raise RefusedError(
                "bad_command",
                f"joint {self.name} is a velocity joint: send a velocity, not a position",
            )
        op, field = self.declaration.move
        return {"op": op, field: self.target_raw(position)}

    def turn_command(self, velocity: float) -> dict[str, Any]:
        """The kind's own command that turns a velocity joint at ``velocity`` (SI)."""
        turn = self.declaration.turn
        if self.type != "velocity" or turn is None:
            raise RefusedError(
                "bad_command",
                f"joint {self.name} is a position joint: send a position, not a velocity",
            )
        speed = self.speed_of(velocity)
        self.check_velocity(speed)
        op, field = turn
        return {"op": op, field: speed}

    @property
    def follows(self) -> Literal["position", "velocity"]:
        """What the joint's follow targets in SI are: positions, or speeds (its type's, where
        the family's stream carries both)."""
        return self.declaration.follows_of(self.type) or "velocity"

    def kind_follow(
        self, position: float | None, velocity: float | None
    ) -> tuple[dict[str, Any], float]:
        """The kind's own follow payload nearest a joint follow target (SI), inside what the
        device takes (the stream's limiter then holds it within the joint's limits), and the
        raw value asked for, unclamped: ``(payload, raw)``."""
        declaration = self.declaration
        if self.follows == "position":
            if position is None:
                raise RefusedError(
                    "bad_command",
                    f"joint {self.name} follows positions: send joint, not joint_velocity",
                )
            low, high = declaration.raw_range
            raw = self.position_raw(position)
            field = declaration.follow_position
            assert field is not None  # ``follows`` says so
            return {field: min(max(round(raw), low), high)}, raw
        if velocity is None or declaration.follow_velocity is None:
            raise RefusedError(
                "bad_command",
                f"joint {self.name} follows speeds: send joint_velocity, not joint",
            )
        speed = self.speed_of(velocity)
        top = declaration.top_speed if declaration.top_speed is not None else math.inf
        return {declaration.follow_velocity: min(max(speed, -top), top)}, speed

    # -- what clients read ---------------------------------------------------------------------

    def state(self, telemetry: Mapping[str, Any]) -> dict[str, Any]:
        """The joint's values in SI from one reading of the device (``None``: not known)."""
        declaration = self.declaration
        position = telemetry.get(declaration.position)
        speed = telemetry.get(declaration.speed_rpm) if declaration.speed_rpm else None
        effort = telemetry.get(declaration.effort) if declaration.effort else None
        target = telemetry.get(self._target_field)
        to_si = self.velocity_si if self.type == "velocity" else self.position_si
        return {
            "name": self.name,
            "type": self.type,
            "unit": self.unit,
            "position": None if position is None else published(self.position_si(position)),
            "velocity": None if speed is None else published(self.velocity_si(speed)),
            "effort": None
            if effort is None
            else published(math.copysign(1.0, self.scale) * effort * declaration.effort_per_raw),
            "target": None if target is None else published(to_si(target)),
        }

    def describe(self) -> dict[str, Any]:
        """What ``info`` says of the joint."""
        return {
            "name": self.name,
            "type": self.type,
            "unit": self.unit,
            "scale": self.scale,
            "offset": self.offset,
            "min": self.min,
            "max": self.max,
            "max_velocity": self.max_velocity,
            "max_acceleration": self.max_acceleration,
            "max_effort": self.max_effort,
            "effort_unit": self.declaration.effort_unit,
            "raw_per_turn": self.raw_per_turn,
            "configured": self.configured,
        }

    def _range(self) -> str:
        return f"{self.min:g}–{self.max:g} {self.unit}"

    def _refusal(
        self, what: str, value: float, unit: str, limit_name: str, limit: float
    ) -> RefusedError:
        value += 0.0  # -0.0 is 0 (shown "-0" beyond a min above it, it read as a sign error)
        shown = f"{value:g}"
        if f"{abs(value):g}" == f"{abs(limit):g}":  # past it by less than six digits show: all,
            shown = repr(published(value))  # to the digits a double keeps through units
        return RefusedError(
            "out_of_range",
            f"joint {self.name}: {what} {shown} {unit} is beyond its {limit_name} {limit:g} {unit}",
        )
