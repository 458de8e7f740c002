"""What ``<prefix>/<gw>/trajectory`` takes: a time-parametrised trajectory for several devices
(``play``), the end of one (``cancel``), and what is playing (``status``).

Rules of this file:

1. Only the trajectory's structure is judged here: one value per device in every list, times
   that only go forward, positions or speeds throughout. A value's range is its device's
   joint's (``busgate.schemas.joints``), and nothing here knows which device is which: the
   gateway checks each device's path against its joint's limits and its kind's follow
   target. Every number must be finite (``CommandModel``) and within ``MAX_MAGNITUDE``
   (``out_of_range``), so no path overflows a float.
2. A trajectory moves positions or, for ZLAC706 devices in velocity mode, speeds (``rpms``,
   any number as a ``Rpm`` is): never both. ``units`` says what the numbers are: ``raw``
   (the default), each device's own units, positions whole (as every kind's are); or
   ``joint``, each device's joint's SI units (m or rad, per second, per second²), positions
   any number. A joint trajectory moves positions: speeds are a velocity joint's own
   command or follow stream, not a trajectory's.
3. A structural problem is a ``ValueError`` raised by a validator (pydantic's ``value_error``:
   ``bad_command``), its one line naming the point and field; too many points is pydantic's
   own ``too_long`` (``out_of_range``, ``busgate.schemas.validation.refusal_code``).
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    WithJsonSchema,
    model_validator,
)

from busgate.schemas.base import CommandModel
from busgate.schemas.config import Name

#: The most points one trajectory may have.
MAX_TRAJECTORY_POINTS = 10_000
#: The largest payload the trajectory key takes, in bytes (every other key takes the API's
#: ``MAX_PAYLOAD``, ``busgate.schemas.payload``).
MAX_TRAJECTORY_PAYLOAD = 1024 * 1024
#: The longest a trajectory may last, and the longest ``goal_time_s``, in seconds: a bound a
#: robot's plans stay far inside, which keeps every time a float of fine resolution.
MAX_TRAJECTORY_S = 3600.0

#: How the points are joined: straight lines, Hermite cubics (positions and velocities) or
#: quintics (positions, velocities and accelerations).
Interpolation = Literal["linear", "cubic", "quintic"]
#: The field of each point that carries the devices' values.
ValuesField = Literal["positions", "rpms"]
#: What a play's numbers are (rule 2): each device's own units, or its joint's SI units.
Units = Literal["raw", "joint"]

#: A point's lists that carry one value per device.
_PER_DEVICE_FIELDS: tuple[str, ...] = ("positions", "rpms", "velocities", "accelerations")

#: The largest magnitude of a point's value, velocity (units/s) or acceleration (units/s²):
#: past every kind's range by far (each kind checks its own), and small enough that a path's
#: polynomial stays a float with room to spare (a segment of ``MAX_TRAJECTORY_S`` at this
#: acceleration has coefficients of 1e16, where 1e308 would overflow to infinity).
MAX_MAGNITUDE = 1e9

NonNegative = Annotated[float, Field(ge=0)]
Magnitude = Annotated[float, Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
WholeMagnitude = Annotated[int, Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
#: Seconds within a trajectory's reach.
Seconds = Annotated[float, Field(ge=0, le=MAX_TRAJECTORY_S)]


def _number_kind(value: Any) -> str:
    """An integer is validated as one (its bound past a double's reach is ``out_of_range``),
    anything else as a float (a ``True`` or a string: ``bad_command``)."""
    return "whole" if isinstance(value, int) and not isinstance(value, bool) else "number"


#: A position: a whole number as given, or a float (the play's ``units`` says which it may be:
#: ``TrajectoryPlay``); within ``MAX_MAGNITUDE`` either way.
Position = Annotated[
    Annotated[WholeMagnitude, Tag("whole")] | Annotated[Magnitude, Tag("number")],
    Discriminator(_number_kind),
    WithJsonSchema({"type": "number", "minimum": -MAX_MAGNITUDE, "maximum": MAX_MAGNITUDE}),
]


class TrajectoryPoint(BaseModel):
    """Where the devices are at ``t_s`` seconds from the trajectory's start, one value per
    device in the play's ``units`` (the manual's, or the joint's SI units): ``positions``, or
    ``rpms`` for ZLAC706 devices in velocity mode; optionally their velocities (units per
    second) and accelerations (units/s²)."""

    model_config = CommandModel.model_config

    t_s: Seconds
    positions: list[Position] | None = None
    rpms: list[Magnitude] | None = None
    velocities: list[Magnitude] | None = None
    accelerations: list[Magnitude] | None = None

    @model_validator(mode="after")
    def _positions_or_rpms(self) -> TrajectoryPoint:
        if self.positions is not None and self.rpms is not None:
            raise ValueError("a point gives positions or rpms, not both")
        if self.positions is None and self.rpms is None:
            raise ValueError("a point needs positions (or rpms, for a speed trajectory)")
        return self

    @property
    def values_field(self) -> ValuesField:
        """Which field carries the point's values."""
        return "positions" if self.positions is not None else "rpms"

    @property
    def values(self) -> Sequence[float]:
        """The devices' positions or speeds, whichever the point gives."""
        values = self.positions if self.positions is not None else self.rpms
        assert values is not None  # the validator's rule
        return values


class TrajectoryPlay(CommandModel):
    """Play ``points`` on ``devices`` from ``start_at``: each device's value at a time is the
    interpolant through its points (``interpolation``; by default ``cubic`` when any point
    gives velocities, else ``linear``), starting from where the device is. ``units`` says
    whether the numbers are each device's own units (``raw``) or its joint's SI units
    (``joint``: positions in m or rad, velocities per second, accelerations per second²). The
    tolerances are one value per device, in the same units: how far it may be from the path
    while playing, and from the last point once ``goal_time_s`` has passed after it."""

    #: The JSON Schema's rule 2: positions are whole numbers unless ``units`` is ``joint``.
    model_config = ConfigDict(
        json_schema_extra={
            "anyOf": [
                {"type": "object", "properties": {"units": {"const": "joint"}},
                 "required": ["units"]},
                {"type": "object", "properties": {"points": {"items": {
                    "type": "object", "properties": {"positions": {"anyOf": [
                        {"type": "array", "items": {"type": "integer"}}, {"type": "null"},
                    ]}},
                }}}},
            ]
        }
    )  # fmt: skip

    op: Literal["play"]
    id: Name
    devices: Annotated[list[Name], Field(min_length=1)]
    points: Annotated[list[TrajectoryPoint], Field(min_length=1, max_length=MAX_TRAJECTORY_POINTS)]
    start_at: float | None = Field(default=None, description="When t_s is 0, Unix seconds.")
    interpolation: Interpolation | None = None
    path_tolerance: list[NonNegative] | None = None
    goal_tolerance: list[NonNegative] | None = None
    goal_time_s: Seconds = 0.0
    units: Units = "raw"

    @model_validator(mode="after")
    def _structure(self) -> TrajectoryPlay:
        _check_devices(self.devices)
        for name in ("path_tolerance", "goal_tolerance"):
            _check_length(name, getattr(self, name), len(self.devices))
        if self.units == "joint" and self.values_field == "rpms":
            raise ValueError(
                'units "joint" moves positions (SI), not rpms: a velocity joint takes '
                '{"op": "joint", "velocity": v} or a follow stream of {"joint_velocity": v}'
            )
        for index, point in enumerate(self.points):
            _check_point(index, point, self.values_field, len(self.devices))
            if self.units == "raw":
                _check_whole(index, point)
        for index, (before, after) in enumerate(pairwise(self.points), 1):
            if after.t_s <= before.t_s:
                raise ValueError(
                    f"points[{index}].t_s ({after.t_s}) must be after "
                    f"points[{index - 1}].t_s ({before.t_s})"
                )
        return self

    @property
    def values_field(self) -> ValuesField:
        """Whether the trajectory moves ``positions`` or ``rpms`` (rule 2)."""
        return self.points[0].values_field

    @property
    def interpolation_used(self) -> Interpolation:
        """``interpolation``, or by default ``cubic`` when any point gives velocities, else
        ``linear``."""
        if self.interpolation is not None:
            return self.interpolation
        return "cubic" if any(p.velocities is not None for p in self.points) else "linear"


def _check_devices(devices: list[str]) -> None:
    seen: set[str] = set()
    for device in devices:
        if device in seen:
            raise ValueError(f"devices must be distinct: {device} is named twice")
        seen.add(device)


def _check_length(name: str, values: Sequence[float] | None, devices: int) -> None:
    if values is not None and len(values) != devices:
        raise ValueError(f"{name} has {len(values)} values for {devices} devices")


def _check_point(index: int, point: TrajectoryPoint, field: ValuesField, devices: int) -> None:
    """One value per device in each of the point's lists, and the first point's field."""
    if point.values_field != field:
        raise ValueError(
            f"points[{index}] gives {point.values_field} and points[0] {field}: a trajectory "
            "moves positions or speeds, not both"
        )
    for name in _PER_DEVICE_FIELDS:
        _check_length(f"points[{index}].{name}", getattr(point, name), devices)


def _check_whole(index: int, point: TrajectoryPoint) -> None:
    """In raw units positions are whole numbers, as every kind's are (rule 2)."""
    for device, value in enumerate(point.positions or ()):
        if type(value) is not int:
            raise ValueError(
                f"points[{index}].positions[{device}] is {value!r}: raw positions are whole "
                'numbers (with "units": "joint" they are SI numbers)'
            )


class TrajectoryCancel(CommandModel):
    """Stop playing trajectory ``id``."""

    op: Literal["cancel"]
    id: Name


class TrajectoryStatus(CommandModel):
    """What trajectories are playing."""

    op: Literal["status"]


#: What ``<prefix>/<gw>/trajectory`` takes.
TrajectoryCommand = Annotated[
    TrajectoryPlay | TrajectoryCancel | TrajectoryStatus, Field(discriminator="op")
]
TRAJECTORY_COMMAND_ADAPTER: TypeAdapter[TrajectoryCommand] = TypeAdapter(TrajectoryCommand)
