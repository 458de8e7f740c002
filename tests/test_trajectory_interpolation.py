"""The interpolant meets its definition (gateway/trajectory/interpolation.py): linear is
piecewise linear through every point; cubic passes through every point with its velocity (0
where not given); quintic also with its acceleration; before the first point the path leaves
the start at rest (a first point at ``t_s`` = 0 replaces the start); after the last point it
holds. Random point sets (hypothesis): exact values at the knots, continuity there, times
before, between and after the points.

Derivatives are taken numerically on an exact twin of the path: its knots as ``Fraction``s, so
the same formulas evaluate without rounding and a one-sided difference over a step of 1e-20 s
is off the derivative by its truncation error alone (step × the next derivative), where in
floats the rounding would swamp any step small enough."""

from __future__ import annotations

import math
from dataclasses import astuple
from fractions import Fraction
from itertools import pairwise
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.gateway.trajectory.interpolation import INTERPOLATIONS, Knot, Path, paths_of, sent
from busgate.schemas.trajectory import TrajectoryPlay

STEP = Fraction(1, 10**20)


def exact(path: Path) -> Path:
    """The same path (its start knot included) with every number a ``Fraction``."""
    knots = [Knot(*(Fraction(x) for x in astuple(knot))) for knot in path.knots]
    return Path(knots[0].value, knots, path.interpolation)


def derivative(path: Path, t_s: Fraction, side: int) -> Fraction:
    """The one-sided first derivative at ``t_s``, from the left (``side`` -1) or the right."""
    h = side * STEP
    return (path.at(t_s + h) - path.at(t_s)) / h


def second_derivative(path: Path, t_s: Fraction, side: int) -> Fraction:
    h = side * STEP
    return (path.at(t_s + 2 * h) - 2 * path.at(t_s + h) + path.at(t_s)) / h**2


def close(numerical: Fraction, expected: float) -> bool:
    """Within 1e-6 relative (and absolute, for an expected 0)."""
    return math.isclose(numerical, expected, rel_tol=1e-6, abs_tol=1e-6)


# --- random point sets -------------------------------------------------------------------------

gaps = st.floats(0.05, 2.0)
values = st.integers(-5000, 5000)
velocities = st.none() | st.floats(-1000, 1000)
accelerations = st.none() | st.floats(-10_000, 10_000)


@st.composite
def plays(draw: Any, interpolation: str | None = None) -> TrajectoryPlay:
    """A one-device trajectory of 1–6 points (the first at 0 or later), each point with or
    without a velocity and an acceleration."""
    count = draw(st.integers(1, 6))
    times = [0.0 if draw(st.booleans()) else draw(gaps)]
    for _ in range(count - 1):
        times.append(times[-1] + draw(gaps))
    points = []
    for t_s in times:
        point: dict[str, Any] = {"t_s": t_s, "positions": [draw(values)]}
        for name, strategy in (("velocities", velocities), ("accelerations", accelerations)):
            extra = draw(strategy)
            if extra is not None:
                point[name] = [extra]
        points.append(point)
    chosen = draw(st.sampled_from(INTERPOLATIONS)) if interpolation is None else interpolation
    return TrajectoryPlay.model_validate(
        {"op": "play", "id": "p", "devices": ["d"], "points": points, "interpolation": chosen}
    )


def path_of(play: TrajectoryPlay, start: float) -> Path:
    [path] = paths_of(play, [start])
    return path


def wanted(play: TrajectoryPlay, name: str) -> list[tuple[float, float]]:
    """(time, the velocity or acceleration wanted there): 0 at the start when the first point
    is later, then each point's own, 0 where it gives none."""
    at_start = [(0.0, 0.0)] if play.points[0].t_s > 0 else []
    given = [(p.t_s, getattr(p, name)[0] if getattr(p, name) else 0.0) for p in play.points]
    return at_start + given


@given(plays(), values)
def test_the_value_at_every_point_is_the_points_own(play, start):
    path = path_of(play, start)
    assert [path.at(p.t_s) for p in play.points] == [p.values[0] for p in play.points]
    assert path.at(0) == (start if play.points[0].t_s > 0 else play.points[0].values[0])


@given(plays(), values)
def test_the_path_is_continuous_at_every_point(play, start):
    path = path_of(play, start)
    scale = max(abs(k.value) for k in path.knots) + 1
    for knot in path.knots:
        for beside in (math.nextafter(knot.t_s, -math.inf), math.nextafter(knot.t_s, math.inf)):
            assert abs(path.at(beside) - knot.value) <= 1e-9 * scale


@given(plays(), values, st.lists(st.floats(-10, 20), max_size=20))
def test_before_the_start_it_holds_the_start_after_the_end_the_last_point(play, start, times):
    path = path_of(play, start)
    first, last = path.knots[0].value, play.points[-1].values[0]
    for t_s in times:
        if t_s <= 0:
            assert path.at(t_s) == first
        elif t_s >= play.points[-1].t_s:
            assert path.at(t_s) == last
    assert path.end_s == play.points[-1].t_s


@given(plays("linear"), values, st.lists(st.floats(0, 1), min_size=1, max_size=10))
def test_linear_is_the_straight_line_between_each_two_points(play, start, fractions):
    path = exact(path_of(play, start))
    for a, b in pairwise(path.knots):
        samples = [path.at(a.t_s + Fraction(f) * (b.t_s - a.t_s)) for f in sorted(fractions)]
        assert samples == [a.value + Fraction(f) * (b.value - a.value) for f in sorted(fractions)]
        assert samples == sorted(samples) or samples == sorted(samples, reverse=True)


def sides(path: Path, t_s: float) -> list[int]:
    """The sides of a knot's time on which the path has a segment (-1: before, 1: after)."""
    return [side for side, inside in ((-1, t_s > 0), (1, t_s < path.end_s)) if inside]


@pytest.mark.parametrize("interpolation", ["cubic", "quintic"])
@given(data=st.data(), start=values)
def test_cubic_and_quintic_pass_every_point_at_its_velocity_or_at_rest(interpolation, data, start):
    play = data.draw(plays(interpolation))
    path = exact(path_of(play, start))
    for t_s, velocity in wanted(play, "velocities"):
        for side in sides(path, t_s):
            assert close(derivative(path, Fraction(t_s), side), velocity), (t_s, side)


@given(plays("quintic"), values)
def test_quintic_meets_every_points_acceleration_or_zero(play, start):
    path = exact(path_of(play, start))
    for t_s, acceleration in wanted(play, "accelerations"):
        for side in sides(path, t_s):
            assert close(second_derivative(path, Fraction(t_s), side), acceleration), (t_s, side)


# --- the start, the end, the refusals -----------------------------------------------------------


@pytest.mark.parametrize("interpolation", INTERPOLATIONS)
def test_the_path_leaves_the_start_at_rest_unless_a_first_point_at_0_replaces_it(interpolation):
    later = Path(100.0, [Knot(1.0, 500.0, 300.0, 50.0)], interpolation)
    assert later.knots[0] == Knot(0.0, 100.0) and later.at(0) == 100.0 and later.at(1) == 500.0
    if interpolation != "linear":
        assert close(derivative(exact(later), Fraction(0), 1), 0)
    at_zero = Path(100.0, [Knot(0.0, 250.0), Knot(1.0, 500.0)], interpolation)
    assert at_zero.knots[0] == Knot(0.0, 250.0) and at_zero.at(0) == 250.0 == at_zero.at(-5)


def test_after_the_last_point_the_path_holds_even_when_it_arrives_moving():
    path = Path(0.0, [Knot(1.0, 500.0, velocity=200.0)], "cubic")
    assert [path.at(t) for t in (1.0, 1.5, 1e9)] == [500.0] * 3
    assert close(derivative(exact(path), Fraction(1), -1), 200.0)


def test_a_path_needs_points_at_strictly_increasing_times_from_0():
    for knots in (
        [],
        [Knot(1.0, 0.0), Knot(1.0, 1.0)],
        [Knot(2.0, 0.0), Knot(1.0, 1.0)],
        [Knot(-0.5, 0.0)],
    ):
        with pytest.raises(ValueError, match="strictly increasing"):
            Path(0.0, knots, "linear")
    with pytest.raises(ValueError, match="linear, cubic, quintic"):
        Path(0.0, [Knot(1.0, 0.0)], "spline")


def test_paths_of_makes_one_path_per_device_from_its_start():
    play = TrajectoryPlay.model_validate(
        {
            "op": "play",
            "id": "p",
            "devices": ["la1", "s1"],
            "interpolation": "quintic",
            "points": [
                {"t_s": 0.5, "positions": [500, 2048], "velocities": [10, -20]},
                {"t_s": 1.5, "positions": [1500, 3000], "accelerations": [1.5, 0]},
            ],
        }
    )
    la1, s1 = paths_of(play, [0.0, 2000.0])
    assert la1.knots == (Knot(0.0, 0.0), Knot(0.5, 500, 10, 0), Knot(1.5, 1500, 0, 1.5))
    assert s1.knots == (Knot(0.0, 2000.0), Knot(0.5, 2048, -20, 0), Knot(1.5, 3000, 0, 0))
    assert la1.interpolation == s1.interpolation == "quintic"
    with pytest.raises(ValueError, match="1 start values for 2 devices"):
        paths_of(play, [0.0])


def test_paths_of_uses_the_default_interpolation_and_takes_speeds():
    play = TrajectoryPlay.model_validate(
        {
            "op": "play",
            "id": "p",
            "devices": ["wheel"],
            "points": [{"t_s": 1.0, "rpms": [120.5]}, {"t_s": 2.0, "rpms": [-30.25]}],
        }
    )
    [wheel] = paths_of(play, [0.0])
    assert wheel.interpolation == "linear"
    assert [wheel.at(t) for t in (0.5, 1.0, 1.5, 3.0)] == [60.25, 120.5, 45.125, -30.25]


# --- what is sent ------------------------------------------------------------------------------


@given(st.integers(-(2**52) + 1, 2**52 - 1))
def test_sent_rounds_halves_away_from_zero(whole):
    assert sent(whole + 0.5) == (whole + 1 if whole >= 0 else whole)
    assert sent(float(whole)) == whole


@given(st.floats(-1e15, 1e15))
def test_sent_is_the_nearest_whole_unit(value):
    nearest = sent(value)
    assert abs(Fraction(value) - nearest) <= Fraction(1, 2)
    if abs(Fraction(value) - nearest) == Fraction(1, 2):
        assert abs(nearest) > abs(value)
