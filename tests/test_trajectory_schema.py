"""The trajectory key's commands (schemas/trajectory.py): the contract's example, the defaults,
every structural refusal with its one line and its code (``refusal_code``: ``out_of_range``
for too many points, ``bad_command`` for structure), strictness, and the largest trajectory
the key takes, validated in well under a second."""

from __future__ import annotations

import json
import time
from typing import Any

import pytest
from pydantic import ValidationError

from busgate.schemas.trajectory import (
    MAX_TRAJECTORY_PAYLOAD,
    MAX_TRAJECTORY_POINTS,
    TRAJECTORY_COMMAND_ADAPTER,
    TrajectoryCancel,
    TrajectoryPlay,
    TrajectoryStatus,
)
from busgate.schemas.validation import describe_validation_error, refusal_code

EXAMPLE: dict[str, Any] = {
    "op": "play",
    "client": "arm-ctl",
    "id": "pick-1",
    "devices": ["la1", "la2", "s1"],
    "points": [
        {"t_s": 0.0, "positions": [500, 500, 2048]},
        {"t_s": 0.8, "positions": [1500, 900, 3000], "velocities": [0, 0, 0]},
        {"t_s": 1.6, "positions": [1000, 700, 2500]},
    ],
    "start_at": 1796150000.250,
    "interpolation": "cubic",
    "path_tolerance": [100, 100, 200],
    "goal_tolerance": [10, 10, 20],
    "goal_time_s": 0.5,
}


def play(**changes: Any) -> dict[str, Any]:
    """The contract's example with ``changes`` (a value of ``None`` leaves the field out)."""
    merged = EXAMPLE | changes
    return {name: value for name, value in merged.items() if value is not None}


def points(*changes: dict[str, Any]) -> list[dict[str, Any]]:
    """The example's points, the i-th updated with ``changes[i]`` (``None``: field left out)."""
    merged = [point | change for point, change in zip(EXAMPLE["points"], changes, strict=True)]
    return [{name: value for name, value in p.items() if value is not None} for p in merged]


def refused(value: Any) -> ValidationError:
    with pytest.raises(ValidationError) as caught:
        TRAJECTORY_COMMAND_ADAPTER.validate_python(value)
    return caught.value


# --- what is taken --------------------------------------------------------------------------


def test_the_contracts_example_validates_from_json_and_from_the_parsed_object():
    command = TRAJECTORY_COMMAND_ADAPTER.validate_json(json.dumps(EXAMPLE))
    assert command == TRAJECTORY_COMMAND_ADAPTER.validate_python(EXAMPLE)
    assert isinstance(command, TrajectoryPlay)
    assert (command.client, command.id, command.devices) == (
        "arm-ctl",
        "pick-1",
        ["la1", "la2", "s1"],
    )
    assert [p.t_s for p in command.points] == [0.0, 0.8, 1.6]
    assert command.points[1].velocities == [0, 0, 0] and command.points[0].velocities is None
    assert (command.interpolation_used, command.values_field) == ("cubic", "positions")
    assert command.points[2].values == [1000, 700, 2500]
    assert (command.start_at, command.goal_time_s) == (1796150000.25, 0.5)


def test_cancel_and_status():
    cancel = TRAJECTORY_COMMAND_ADAPTER.validate_python(
        {"op": "cancel", "id": "pick-1", "client": "arm-ctl"}
    )
    assert isinstance(cancel, TrajectoryCancel) and cancel.id == "pick-1"
    assert isinstance(
        TRAJECTORY_COMMAND_ADAPTER.validate_python({"op": "status"}), TrajectoryStatus
    )


def test_the_optional_fields_have_their_defaults():
    command = TrajectoryPlay.model_validate(
        play(
            client=None,
            start_at=None,
            interpolation=None,
            path_tolerance=None,
            goal_tolerance=None,
            goal_time_s=None,
        )
    )
    assert (command.client, command.start_at, command.interpolation) == (None, None, None)
    assert (command.path_tolerance, command.goal_tolerance, command.goal_time_s) == (
        None,
        None,
        0.0,
    )


@pytest.mark.parametrize(("given", "velocities", "used"), [
    (None, True, "cubic"), (None, False, "linear"), ("linear", True, "linear"),
    ("cubic", False, "cubic"), ("quintic", False, "quintic"),
])  # fmt: skip
def test_the_interpolation_used_is_cubic_by_default_when_any_point_gives_velocities(
    given, velocities, used
):
    with_or_without = points({}, {"velocities": [0, 0, 0] if velocities else None}, {})
    command = TrajectoryPlay.model_validate(play(interpolation=given, points=with_or_without))
    assert command.interpolation_used == used


def test_a_speed_trajectory_takes_any_number_in_rpms():
    speeds = [
        {"t_s": 0.5, "rpms": [12.5, -3]},
        {"t_s": 1.0, "rpms": [0, 100.25], "accelerations": [1, 2]},
    ]
    command = TrajectoryPlay.model_validate(
        play(devices=["wheel", "drive"], points=speeds, path_tolerance=None, goal_tolerance=None)
    )
    assert command.values_field == "rpms"
    assert [p.values for p in command.points] == [[12.5, -3], [0, 100.25]]


def test_velocities_and_accelerations_are_taken_with_any_interpolation():
    extras = points({"accelerations": [1, 2, 3]}, {"velocities": [1, 2, 3]}, {})
    for interpolation in ("linear", "cubic", "quintic"):
        TrajectoryPlay.model_validate(play(interpolation=interpolation, points=extras))


# --- what is refused, and how -----------------------------------------------------------------

STRUCTURE = [
    (play(points=points({}, {"t_s": 0.0}, {})),
     "points[1].t_s (0.0) must be after points[0].t_s (0.0)"),
    (play(points=points({}, {}, {"t_s": 0.5})),
     "points[2].t_s (0.5) must be after points[1].t_s (0.8)"),
    (play(points=points({}, {"positions": [1, 2]}, {})),
     "points[1].positions has 2 values for 3 devices"),
    (play(points=points({}, {"velocities": [0, 0, 0, 0]}, {})),
     "points[1].velocities has 4 values for 3 devices"),
    (play(points=points({}, {}, {"accelerations": [1]})),
     "points[2].accelerations has 1 values for 3 devices"),
    (play(points=points({}, {"positions": None, "rpms": [1.5, 2, 3]}, {})),
     "points[1] gives rpms and points[0] positions: a trajectory moves positions or speeds, "
     "not both"),
    (play(points=points({}, {}, {"rpms": [1, 2, 3]})),
     "points.2: a point gives positions or rpms, not both"),
    (play(points=points({"positions": None}, {}, {})),
     "points.0: a point needs positions (or rpms, for a speed trajectory)"),
    (play(devices=["la1", "la2", "la1"]), "devices must be distinct: la1 is named twice"),
    (play(path_tolerance=[100, 100]), "path_tolerance has 2 values for 3 devices"),
    (play(goal_tolerance=[1, 1, 1, 1]), "goal_tolerance has 4 values for 3 devices"),
]  # fmt: skip


@pytest.mark.parametrize(("value", "message"), STRUCTURE, ids=lambda v: str(v)[-40:])
def test_a_structural_problem_is_a_bad_command_named_in_one_line(value, message):
    error = refused(value)
    assert refusal_code(error) == "bad_command"
    assert [e["type"] for e in error.errors()] == ["value_error"]
    line = describe_validation_error(error)
    assert "\n" not in line and line.startswith("play") and line.endswith(message)


def long_play(count: int, devices: int = 3) -> dict[str, Any]:
    return {
        "op": "play",
        "id": "long",
        "devices": [f"d{i}" for i in range(devices)],
        "points": [{"t_s": i * 0.01, "positions": [i % 2000] * devices} for i in range(count)],
    }


def test_more_points_than_the_limit_are_out_of_range():
    error = refused(long_play(MAX_TRAJECTORY_POINTS + 1))
    assert [e["type"] for e in error.errors()] == ["too_long"]
    assert refusal_code(error) == "out_of_range"
    assert "at most 10000 items" in describe_validation_error(error)


@pytest.mark.parametrize("value", [
    play(points=[]), play(devices=[], points=[{"t_s": 0, "positions": []}], path_tolerance=None,
                          goal_tolerance=None),
    play(points=points({"t_s": -0.1}, {}, {})), play(goal_time_s=-1),
    play(path_tolerance=[100, -1, 200]), play(goal_tolerance=[0, 0, -0.5]),
    # past an hour: every tick of the grid is checked before a play is accepted, and a point
    # at 1e300 s would hold the gateway's trajectory worker (and every cancel) for ever
    play(points=points({}, {}, {"t_s": 3600.5})), play(points=points({}, {}, {"t_s": 1e300})),
    play(goal_time_s=3601),
])  # fmt: skip
def test_a_value_outside_its_bounds_is_out_of_range(value):
    assert refusal_code(refused(value)) == "out_of_range"


@pytest.mark.parametrize("value", [
    play(points=points({"positions": [500.0, 500, 2048]}, {}, {})),
    play(points=points({"positions": [True, 500, 2048]}, {}, {})),
    play(points=points({"t_s": "0"}, {}, {})),
    play(points=points({}, {"velocities": [0, float("nan"), 0]}, {})),
    play(points=points({}, {}, {"accelerations": [0, 0, float("inf")]})),
    play(points=points({"t_s": float("inf")}, {}, {})),
    play(start_at=float("nan")), play(goal_time_s=float("inf")),
    play(path_tolerance=[100, float("inf"), 1]),
    play(points=points({}, {"speed": 3}, {})), play(extra=1),
    play(interpolation="spline"), play(id=None), play(id="pick 1"), play(id="x" * 65),
    play(devices=["la/1", "la2", "s1"]), play(client="arm ctl"),
    {"op": "cancel"}, {"op": "cancel", "id": "a", "points": []}, {"op": "status", "id": "a"},
    {"op": "pause", "id": "a"},
])  # fmt: skip
def test_what_is_not_the_contracts_shape_is_a_bad_command(value):
    assert refusal_code(refused(value)) == "bad_command"


# --- the largest trajectory the key takes --------------------------------------------------------


def timed(call: Any, *args: Any) -> tuple[Any, float]:
    start = time.perf_counter()
    result = call(*args)
    return result, time.perf_counter() - start


def test_the_most_points_validate_in_well_under_a_second():
    value = long_play(MAX_TRAJECTORY_POINTS)
    command, seconds = timed(TRAJECTORY_COMMAND_ADAPTER.validate_python, value)
    print(f"{MAX_TRAJECTORY_POINTS} points × 3 devices validated in {seconds * 1000:.0f} ms")
    assert len(command.points) == MAX_TRAJECTORY_POINTS and seconds < 1


def test_a_payload_of_about_the_keys_limit_validates_in_well_under_a_second():
    value = long_play(MAX_TRAJECTORY_POINTS)
    for i, point in enumerate(value["points"]):
        point["t_s"] = i * 0.0123456789
        point["velocities"] = [-123.456789, -122.456789, -121.456789]
    payload = json.dumps(value, separators=(",", ":")).encode()
    assert 0.9 * MAX_TRAJECTORY_PAYLOAD < len(payload) <= MAX_TRAJECTORY_PAYLOAD == 1024 * 1024
    command, from_json = timed(TRAJECTORY_COMMAND_ADAPTER.validate_json, payload)
    parsed, loads = timed(json.loads, payload)
    _, from_object = timed(TRAJECTORY_COMMAND_ADAPTER.validate_python, parsed)
    print(
        f"{len(payload)} bytes: validate_json {from_json * 1000:.0f} ms, json.loads "
        f"{loads * 1000:.0f} ms + validate_python {from_object * 1000:.0f} ms"
    )
    assert command.interpolation_used == "cubic"
    assert from_json < 1 and loads + from_object < 1
