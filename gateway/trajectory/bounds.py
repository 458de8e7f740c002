"""Whether every value of a trajectory's path is one its device takes, found per segment of the
path, never tick by tick: a one-hour point costs what a point a second away does.

Rules of this file:

1. Pure, as ``interpolation`` is: a path and a predicate in, a value out.
2. A segment's polynomial is written in Bernstein form over its ``s`` in [0, 1]: the values it
   takes lie between its least and greatest coefficient, and its first and last coefficients
   are values it takes (the knots' own values are looked at first: a form's last
   coefficient is a sum, rounded). A segment whose bounds the device takes is done; one
   whose end the device refuses has that value to show; otherwise its two halves (de
   Casteljau) are looked at, whose bounds close in on its values, down to ``MAX_DEPTH``
   halvings, past which the bound itself is taken as a value (it is within a rounding error
   of one).
3. What is checked is the whole continuous path, so a value any tick could send is in it
   (every tick samples the path, ``trajectory_ticks`` rule 2). It is the stricter check: an
   overshoot that falls between two ticks is refused too.
4. The device's accepted values are a range (``takes`` of two values means ``takes`` of every
   value between them), as every kind's position and speed ranges are.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from itertools import pairwise
from math import comb

from busgate.gateway.trajectory.interpolation import Path

#: Halvings of a segment past which its bound is taken as a value it reaches (rule 2): a
#: segment's bound is then within 4⁻⁴⁰ of its span of values from the truth.
MAX_DEPTH = 40

Takes = Callable[[float], bool]


def value_refused(path: Path, takes: Takes) -> float | None:
    """A value ``path`` reaches (to within a rounding error) that ``takes`` refuses, or
    ``None`` when it takes every value of the path."""
    knots = [knot.value for knot in path.knots]
    forms = [bernstein(segment) for segment in path.segments]
    least = min(knots + [min(form) for form in forms])
    greatest = max(knots + [max(form) for form in forms])
    if takes(least) and takes(greatest):  # the usual case: one look for the whole path
        return None
    for value in knots:  # exactly what the path takes there (a form's end is rounded)
        if not takes(value):
            return value
    for form in forms:
        refused = _refused_in(form, takes, 0)
        if refused is not None:
            return refused
    return None


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


def _refused_in(form: list[float], takes: Takes, depth: int) -> float | None:
    least, greatest = min(form), max(form)
    if takes(least) and takes(greatest):
        return None
    for end in (form[0], form[-1]):  # values the segment takes (rule 2)
        if not takes(end):
            return end
    if depth == MAX_DEPTH:
        return greatest if not takes(greatest) else least
    left, right = _halves(form)
    refused = _refused_in(left, takes, depth + 1)
    return refused if refused is not None else _refused_in(right, takes, depth + 1)


def _halves(form: list[float]) -> tuple[list[float], list[float]]:
    """The Bernstein forms of the polynomial over [0, ½] and [½, 1] (de Casteljau)."""
    left, right, row = [form[0]], [form[-1]], form
    while len(row) > 1:
        row = [(a + b) / 2 for a, b in pairwise(row)]
        left.append(row[0])
        right.append(row[-1])
    return left, right[::-1]
