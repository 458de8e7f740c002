"""Whether every value of a trajectory's path, and of its velocity and acceleration, is one its
device takes, found per segment of the path, never tick by tick: a one-hour point costs what a
point a second away does.

Rules of this file:

1. Pure, as ``interpolation`` is: a path and a predicate in, a value out.
2. A segment's polynomial is written in Bernstein form over its ``s`` in [0, 1]: the values it
   takes lie between its least and greatest coefficient, and its first and last coefficients
   are values it takes (the knots' own values are looked at first: a form's last
   coefficient is a sum, rounded). A segment whose bounds the device takes is done; one
   whose end the device refuses has that value to show; otherwise its two halves (de
   Casteljau) are looked at, whose bounds close in on its values, down to ``MAX_DEPTH``
   halvings, past which the bound itself is taken as a value (it is within a rounding error
   of one). What is refused comes with when the path reaches it (``Refused.t_s``).
3. What is checked is the whole continuous path, so a value any tick could send is in it
   (every tick samples the path, ``trajectory_ticks`` rule 2). It is the stricter check: an
   overshoot that falls between two ticks is refused too.
4. The device's accepted values are a range (``takes`` of two values means ``takes`` of every
   value between them), as every kind's position and speed ranges and every joint's limits
   are.
5. A path's velocity and acceleration (``rate_refused``) are its segments' derivatives in
   time, each a polynomial bounded the same way (rule 2). They are the segments' own: the
   corners where two segments meet (a linear path's, or a last point reached moving, after
   which the path holds) are steps no finite bound holds, and are not looked at. A derivative
   that is not a finite number (points closer in time than a float can divide by) is refused
   as infinite.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from math import comb

from busgate.gateway.trajectory.interpolation import Path

#: Halvings of a segment past which its bound is taken as a value it reaches (rule 2): a
#: segment's bound is then within 4⁻⁴⁰ of its span of values from the truth.
MAX_DEPTH = 40

Takes = Callable[[float], bool]


@dataclass(frozen=True, slots=True)
class Refused:
    """A value the path reaches (to within a rounding error) that the device refuses, and
    when, in seconds from the trajectory's start."""

    value: float
    t_s: float


def value_refused(path: Path, takes: Takes) -> float | None:
    """A value ``path`` reaches (to within a rounding error) that ``takes`` refuses, or
    ``None`` when it takes every value of the path."""
    found = refusal(path, takes)
    return None if found is None else found.value


def refusal(path: Path, takes: Takes) -> Refused | None:
    """``value_refused``, with when the path reaches the value."""
    knots = [knot.value for knot in path.knots]
    forms = [bernstein(segment) for segment in path.segments]
    least = min(knots + [min(form) for form in forms])
    greatest = max(knots + [max(form) for form in forms])
    if takes(least) and takes(greatest):  # the usual case: one look for the whole path
        return None
    for knot in path.knots:  # exactly what the path takes there (a form's end is rounded)
        if not takes(knot.value):
            return Refused(knot.value, knot.t_s)
    for (a, b), form in zip(pairwise(path.knots), forms, strict=True):
        found = _refused_in(form, takes, 0, 0.0, 1.0)
        if found is not None:
            return Refused(found[0], a.t_s + found[1] * (b.t_s - a.t_s))
    return None


def rate_refused(path: Path, order: int, takes: Takes) -> Refused | None:
    """A value of the path's ``order``-th derivative in time (1: its velocity, units per
    second; 2: its acceleration, per second²) that ``takes`` refuses, segment by segment
    (rule 5), or ``None`` when it takes every one."""
    for (a, b), segment in zip(pairwise(path.knots), path.segments, strict=True):
        form = bernstein(derivative(segment, order, b.t_s - a.t_s))
        if not all(math.isfinite(c) for c in form):
            return Refused(math.inf, a.t_s)
        found = _refused_in(form, takes, 0, 0.0, 1.0)
        if found is not None:
            return Refused(found[0], a.t_s + found[1] * (b.t_s - a.t_s))
    return None


def rate_bounds(path: Path, order: int) -> list[tuple[float, float]]:
    """Each segment's bounds of the path's ``order``-th derivative in time: its Bernstein
    form's least and greatest coefficient (rule 2), between which its values lie."""
    bounds = []
    for (a, b), segment in zip(pairwise(path.knots), path.segments, strict=True):
        form = bernstein(derivative(segment, order, b.t_s - a.t_s))
        bounds.append((min(form), max(form)))
    return bounds


def derivative(coefficients: Sequence[float], order: int, span: float) -> list[float]:
    """The power coefficients in ``s`` of the ``order``-th derivative in time of the segment
    ``coefficients`` (in ``s``, which runs from 0 to 1 over ``span`` seconds).

    >>> derivative([1.0, 4.0, 3.0], 1, 2.0)  # 1 + 4s + 3s², s = t/2: (4 + 6s) / 2
    [2.0, 3.0]
    >>> derivative([1.0, 4.0], 2, 2.0)
    [0.0]
    """
    rows = list(coefficients)
    for _ in range(order):
        rows = [k * rows[k] / span for k in range(1, len(rows))]
    return rows or [0.0]


def bernstein(coefficients: Sequence[float]) -> list[float]:
    """The Bernstein coefficients over [0, 1] of the polynomial ``coefficients`` (power basis,
    constant first).

    >>> bernstein([0.0, 2.0, -1.0])  # 2s - s²: 0 at 0, 1 at 1, at most 1 between
    [0.0, 1.0, 1.0]
    """
    rows = _to_bernstein(len(coefficients) - 1)
    return [sum(w * c for w, c in zip(row, coefficients, strict=False)) for row in rows]


@functools.cache
def _to_bernstein(n: int) -> tuple[tuple[float, ...], ...]:
    """The weights that make a degree-``n`` polynomial's Bernstein coefficients from its power
    coefficients: row ``i`` holds C(i, j) / C(n, j) for j ≤ i."""
    return tuple(tuple(comb(i, j) / comb(n, j) for j in range(i + 1)) for i in range(n + 1))


def _refused_in(
    form: list[float], takes: Takes, depth: int, low: float, high: float
) -> tuple[float, float] | None:
    """A value the polynomial ``form`` (Bernstein, over ``s`` in [``low``, ``high``]) takes
    that ``takes`` refuses, with its ``s``; ``None`` when there is none (rule 2)."""
    least, greatest = min(form), max(form)
    if takes(least) and takes(greatest):
        return None
    for end, s in ((form[0], low), (form[-1], high)):  # values the segment takes (rule 2)
        if not takes(end):
            return end, s
    middle = (low + high) / 2
    if depth == MAX_DEPTH:
        return (greatest if not takes(greatest) else least), middle
    left, right = _halves(form)
    refused = _refused_in(left, takes, depth + 1, low, middle)
    return refused if refused is not None else _refused_in(right, takes, depth + 1, middle, high)


def _halves(form: list[float]) -> tuple[list[float], list[float]]:
    """The Bernstein forms of the polynomial over [0, ½] and [½, 1] (de Casteljau)."""
    left, right, row = [form[0]], [form[-1]], form
    while len(row) > 1:
        row = [(a + b) / 2 for a, b in pairwise(row)]
        left.append(row[0])
        right.append(row[-1])
    return left, right[::-1]
