"""A path's values against a device's range, found per segment (gateway/trajectory/bounds.py):
random paths of every interpolation against a range, compared with the path sampled densely;
the cost counted in looks at the range, not in time, whatever the path's duration; and the
bounds of its derivatives (a joint's velocity and acceleration limits) against its sampled
rates."""

from __future__ import annotations

import math
from itertools import pairwise

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.gateway.trajectory.bounds import bernstein, rate_bounds, rate_refused, value_refused
from busgate.gateway.trajectory.interpolation import INTERPOLATIONS, Knot, Path
from busgate.schemas.trajectory import MAX_MAGNITUDE, MAX_TRAJECTORY_S

LOW, HIGH = 0.0, 2000.0


def within(value: float) -> bool:
    return LOW <= value <= HIGH


def densely(path: Path, per_segment: int = 400) -> list[float]:
    """The path sampled at ``per_segment`` points of each segment and at every knot."""
    samples = []
    for a, b in zip(path.knots, path.knots[1:], strict=False):
        samples += [path.at(a.t_s + (b.t_s - a.t_s) * i / per_segment) for i in range(per_segment)]
    return [*samples, path.knots[-1].value]


knots = st.lists(
    st.tuples(st.floats(0.05, 5.0), st.floats(-500, 2500), st.floats(-3000, 3000),
              st.floats(-30_000, 30_000)),
    min_size=1, max_size=6,
)


def path_of(start: float, points, interpolation: str) -> Path:
    t_s, made = 0.0, []
    for gap, value, velocity, acceleration in points:
        t_s += gap
        made.append(Knot(t_s, value, velocity, acceleration))
    return Path(start, made, interpolation)


@given(st.floats(0, 2000), knots, st.sampled_from(INTERPOLATIONS))
def test_a_value_out_of_range_is_found_and_a_path_within_it_passes(start, points, interpolation):
    path = path_of(start, points, interpolation)
    refused = value_refused(path, within)
    values = densely(path)
    if refused is None:  # every value in range: so is every sample (to a rounding error)
        assert all(LOW - 1e-9 <= v <= HIGH + 1e-9 for v in values)
    else:  # a value out of range the path reaches, to within the dense sampling's step
        assert not within(refused)
        reach = max(values) - min(values)
        assert min(values) - 1e-3 * reach - 1e-9 <= refused <= max(values) + 1e-3 * reach + 1e-9


def test_an_overshoot_between_points_is_found_though_both_points_are_in_range():
    path = Path(1000.0, [Knot(0.2, 1990.0, 8000.0), Knot(0.4, 1990.0)], "cubic")
    refused = value_refused(path, within)
    assert refused is not None and HIGH < refused <= max(densely(path)) + 1e-6


@pytest.mark.parametrize("seconds", [1.0, 3600.0])
def test_the_cost_is_per_segment_whatever_the_duration(seconds):
    """The same shape over a second and over an hour: the same looks at the range, and no
    sample of the path (an hour at 10 ms was 360,000 of them)."""
    path = Path(0.0, [Knot(seconds / 2, 1500.0), Knot(seconds, 300.0)], "quintic")
    looks: list[float] = []

    def counted(value: float) -> bool:
        looks.append(value)
        return within(value)

    sampled = []
    path.at = lambda t_s: sampled.append(t_s)  # type: ignore[method-assign]
    assert value_refused(path, counted) is None
    assert len(looks) == 2 and sampled == []


def test_bernstein_bounds_hold_a_polynomials_values():
    coefficients = [1.0, -4.0, 6.0, -2.0]  # 1 - 4s + 6s² - 2s³
    form = bernstein(coefficients)
    assert form[0] == 1.0 and form[-1] == pytest.approx(1.0)
    for i in range(101):
        s = i / 100
        value = sum(c * s**k for k, c in enumerate(coefficients))
        assert min(form) - 1e-12 <= value <= max(form) + 1e-12


# Every number the play schema takes, at its extremes: the path and its check stay finite.
extreme = st.one_of(st.floats(-MAX_MAGNITUDE, MAX_MAGNITUDE), st.sampled_from(
    [MAX_MAGNITUDE, -MAX_MAGNITUDE, 5e-324, -5e-324, 0.0]))
times = st.one_of(st.floats(5e-324, MAX_TRAJECTORY_S), st.sampled_from([5e-324, 1e-9]))


@given(st.lists(st.tuples(times, extreme, extreme, extreme), min_size=1, max_size=4),
       st.sampled_from(INTERPOLATIONS), extreme)
def test_any_play_the_schema_takes_gives_a_finite_path_and_a_verdict(points, interpolation,
                                                                     start):
    """Values, velocities and accelerations anywhere within ±``MAX_MAGNITUDE`` and points as
    close or as far apart as floats allow (an hour at most): the check answers (a value
    refused, or none) and every value of the path is finite, never an overflow (that was
    ``internal``)."""
    t_s, knots = 0.0, []
    for gap, value, velocity, acceleration in points:
        if t_s + gap <= t_s or t_s + gap > MAX_TRAJECTORY_S:
            break
        t_s += gap
        knots.append(Knot(t_s, round(value), velocity, acceleration))
    if not knots:
        return
    path = Path(start, knots, interpolation)
    refused = value_refused(path, within)
    assert refused is None or (math.isfinite(refused) and not within(refused))
    for knot in path.knots:
        assert math.isfinite(path.at(knot.t_s / 2)) and math.isfinite(path.at(knot.t_s))


# -- the derivative's bounds, per segment --------------------------------------------------------

PER_SEGMENT = 64


def quotients(path: Path, order: int) -> list[tuple[list[float], float]]:
    """Per segment: its difference quotients of ``order`` (1: ``(p(t+h) - p(t)) / h``, 2: the
    second difference over ``h²``) on a grid of ``PER_SEGMENT`` steps, each equal to the
    derivative somewhere on the segment (the mean value theorem), and how far rounding may
    move them (each value's, and each time's times the path's speed)."""
    found = []
    for a, b in pairwise(path.knots):
        h = (b.t_s - a.t_s) / PER_SEGMENT
        values = [path.at(a.t_s + i * h) for i in range(PER_SEGMENT)] + [b.value]
        steps = [(q - p) / h for p, q in pairwise(values)]
        if order == 1:
            made = steps
        else:
            made = [
                (r - 2 * q + p) / h**2
                for p, q, r in zip(values, values[1:], values[2:], strict=False)
            ]
        rounding = max(abs(v) for v in values) + max(abs(v) for v in steps) * b.t_s + 1.0
        found.append((made, 16 * 2.3e-16 * rounding / h**order))
    return found


@pytest.mark.parametrize("order", [1, 2])
@given(st.floats(0, 2000), knots, st.sampled_from(INTERPOLATIONS))
def test_a_segments_derivative_bound_holds_its_sampled_rates(order, start, points, interpolation):
    """Every difference quotient on a segment is within that segment's bound of the
    derivative; a limit twice the largest quotient is never refused, and one below the
    largest is, with a value past it."""
    path = path_of(start, points, interpolation)
    sampled = quotients(path, order)
    for (low, high), (made, slack) in zip(rate_bounds(path, order), sampled, strict=True):
        width = slack + 1e-9 * max(abs(low), abs(high))
        assert all(low - width <= q <= high + width for q in made)
    largest = max(max(abs(q) for q in made) for made, _ in sampled)
    slack = max(s for _, s in sampled)
    limit = 2 * largest + 10 * slack + 1e-6
    assert rate_refused(path, order, lambda rate: abs(rate) <= limit) is None
    if largest > 10 * slack + 1e-6:
        below = largest / 2
        found = rate_refused(path, order, lambda rate: abs(rate) <= below)
        assert found is not None and abs(found.value) > below
        assert 0 <= found.t_s <= path.end_s


def test_a_derivative_past_a_float_is_refused_as_infinite():
    path = Path(0.0, [Knot(5e-324, 1000.0)], "linear")
    found = rate_refused(path, 1, lambda rate: abs(rate) <= 1e6)
    assert found is not None and found.value == math.inf and found.t_s == 0.0
