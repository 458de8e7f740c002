"""A differential drive's arithmetic, exact: a twist to its wheels and back, saturation that
keeps the path's curvature, acceleration steps within the limits on a fake clock, the drive's
samples shared by both wheels of a slot, and odometry from the wheels' positions."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from busgate.gateway.base.drive import Drive
from busgate.gateway.base.kinematics import Geometry, Odometry, Twist
from busgate.schemas.joints import Joint, JointTable
from busgate.schemas.zlac706 import JOINT as ZLAC_JOINT

GEOMETRY = Geometry(wheel_radius_m=0.0825, track_m=0.40, max_linear=1.0, max_angular=2.0,
                    max_linear_accel=0.8, max_angular_accel=3.0, max_wheel=15.0)
speeds = st.floats(-50, 50, allow_nan=False)


@given(speeds, speeds)
def test_a_twist_and_its_wheels_give_each_other_back(linear, angular) -> None:
    twist = GEOMETRY.twist(*GEOMETRY.wheels(Twist(linear, angular)))
    assert twist.linear == pytest.approx(linear, abs=1e-9)
    assert twist.angular == pytest.approx(angular, abs=1e-9)


@given(speeds, speeds)
@example(0.5, -1.0)  # within every limit: as it is
def test_saturation_keeps_the_curvature_and_every_limit(linear, angular) -> None:
    held = GEOMETRY.saturated(Twist(linear, angular))
    assert abs(held.linear) <= 1.0 + 1e-9 and abs(held.angular) <= 2.0 + 1e-9
    assert all(abs(w) <= 15.0 + 1e-9 for w in GEOMETRY.wheels(held))
    # one factor for both: the curvature (and the direction of each) is the one asked for
    assert held.linear * angular == pytest.approx(held.angular * linear, abs=1e-9)
    assert math.copysign(1, held.linear) == math.copysign(1, linear) or held.linear == 0
    if abs(linear) <= 1.0 and abs(angular) <= 2.0 and all(
            abs(w) <= 15 for w in GEOMETRY.wheels(Twist(linear, angular))):
        assert held == Twist(linear, angular)


@pytest.mark.parametrize("linear", [1.6e307, -1.7e308])
def test_a_huge_twist_saturates_to_the_limit_as_a_finite_one_does(linear) -> None:
    """Its wheels' speeds, reckoned from it unscaled, overflowed to infinity: it was scaled
    to 0 (a ROS cmd_vel is not bounded by the schema's MAX_TWIST)."""
    huge = GEOMETRY.saturated(Twist(linear, linear / 10))
    finite = GEOMETRY.saturated(Twist(math.copysign(10.0, linear), math.copysign(1.0, linear)))
    assert huge.linear == pytest.approx(finite.linear) and finite.linear != 0
    assert huge.angular == pytest.approx(finite.angular)


@given(st.floats(-1, 1), st.floats(-2, 2), st.floats(-1, 1), st.floats(-2, 2),
       st.floats(0.001, 0.05))
@pytest.mark.parametrize("wheel_accel", [math.inf, 5.0])
def test_a_step_moves_toward_its_target_within_the_accelerations(
    wheel_accel, v0, w0, v1, w1, dt
) -> None:
    """Within the base's accelerations, and each wheel's (its joint's ``max_acceleration``,
    5 rad/s² here: 0.41 m/s² straight ahead, under the base's 0.8)."""
    geometry = dataclasses.replace(GEOMETRY, max_wheel_accel=wheel_accel)
    step = geometry.step(Twist(v0, w0), Twist(v1, w1), dt)
    assert abs(step.linear - v0) <= 0.8 * dt + 1e-12
    assert abs(step.angular - w0) <= 3.0 * dt + 1e-12
    wheel_steps = zip(geometry.wheels(Twist(v0, w0)), geometry.wheels(step), strict=True)
    assert all(abs(after - before) <= wheel_accel * dt + 1e-9 for before, after in wheel_steps)
    # on the straight line from now to the target, never past it
    along = [(s - a) / (b - a) for s, a, b in ((step.linear, v0, v1), (step.angular, w0, w1))
             if abs(b - a) > 1e-6]
    assert all(-1e-9 <= f <= 1 + 1e-9 for f in along)
    if along:
        assert max(along) - min(along) <= 1e-6


def test_from_rest_a_step_in_twist_becomes_a_ramp_that_keeps_the_curvature() -> None:
    twist, slot = Twist(), 0.02
    seen = []
    for _ in range(200):
        twist = GEOMETRY.step(twist, Twist(0.5, 1.0), slot)
        seen.append(twist)
    assert seen[0] == Twist(0.5 * 0.016 / 0.5 * 1.0, 0.016 * 2.0)  # linear limit: 0.8 × 20 ms
    assert all(t.angular == pytest.approx(2 * t.linear) for t in seen)
    assert seen[-1] == Twist(0.5, 1.0)
    reached = next(i for i, t in enumerate(seen) if t == Twist(0.5, 1.0))
    assert reached == math.ceil(0.5 / (0.8 * slot)) - 1  # 0.5 m/s at 0.8 m/s²: 0.625 s


def wheel_joint(scale: float) -> Joint:
    table = JointTable.model_validate({"unit": "rad", "scale": scale})
    return Joint.of("wheel", ZLAC_JOINT, table)


def test_both_wheels_of_a_slot_get_speeds_of_one_twist_and_the_deadman_ramps_down() -> None:
    left, right = wheel_joint(math.tau / 10_000), wheel_joint(-math.tau / 10_000)  # mirrored
    drive = Drive(GEOMETRY, left, right)
    drive.command(Twist(0.4, 0.0), now=100.0, hold_s=0.5)
    drive.begin(100.0, Twist())
    samples = [(drive.sampler(0)(k * 0.02)["rpm"], drive.sampler(1)(k * 0.02)["rpm"])
               for k in range(1, 60)]
    # straight ahead: the mirrored right motor turns the other way, as much
    assert all(a == pytest.approx(-b) for a, b in samples)
    top = max(a for a, _ in samples)
    assert top == pytest.approx(0.4 / 0.0825 * 60 / math.tau)  # 0.4 m/s reached, in rpm
    held = [a for a, _ in samples]
    peak = held.index(top)
    # after the 0.5 s hold (slot 25), down at 0.8 m/s² like the way up
    assert peak < 25 < len(held) - 1 and held[-1] < top
    assert held[-1] == held[-2] == 0 and drive.finished(100.0 + 60 * 0.02)
    assert not drive.finished(100.0 + 0.4)  # the command still holds


def test_a_halted_drive_is_at_rest_and_its_next_play_starts_from_rest() -> None:
    """A wheel left the play (an e-stop): the drive's twist is 0 at once, a slot sampled
    meanwhile is 0, and it ends as a drive at rest does (two slots at 0): its next play
    starts from 0, not from the twist it had (``drive`` rule 5)."""
    drive = Drive(GEOMETRY, wheel_joint(math.tau / 10_000), wheel_joint(-math.tau / 10_000))
    drive.command(Twist(0.4, 0.0), now=100.0, hold_s=5.0)
    drive.begin(100.0, Twist())
    for k in range(1, 30):
        drive.sample(k * 0.02)
    assert drive.sent.linear > 0.3
    drive.halt()
    assert drive.sent == Twist()
    assert drive.sample(30 * 0.02) == Twist()
    assert not drive.finished(200.0)  # one slot at rest
    assert drive.sample(31 * 0.02) == Twist() and drive.finished(200.0)


def test_odometry_of_a_square_drive_returns_to_the_start() -> None:
    odometry, left, right, at = Odometry(GEOMETRY), 0.0, 0.0, 0.0
    odometry.take(left, right, at)
    side_rad = 1.0 / 0.0825  # 1 m
    quarter = (math.pi / 2) * 0.20 / 0.0825  # each wheel's turn for 90° on the spot
    for _ in range(4):
        for _ in range(50):
            left, right, at = left + side_rad / 50, right + side_rad / 50, at + 0.02
            odometry.take(left, right, at)
        for _ in range(50):
            left, right, at = left - quarter / 50, right + quarter / 50, at + 0.02
            odometry.take(left, right, at)
    pose = odometry.pose
    assert (pose.x, pose.y) == (pytest.approx(0, abs=1e-9), pytest.approx(0, abs=1e-9))
    assert pose.theta == pytest.approx(0, abs=1e-9)
    odometry.reset()
    assert not odometry.take(left, right, at + 1)  # the new start
    assert odometry.pose.x == 0


def test_the_measured_twist_spans_a_window_not_one_step_between_two_heartbeats() -> None:
    """Steps a few ms apart with all the wheel's counts in one of them (as heartbeats of two
    wheels interleave): the twist is the travel over at least 0.1 s, steady."""
    odometry, left, right, at = Odometry(GEOMETRY), 0.0, 0.0, 0.0
    odometry.take(left, right, at)
    speeds = []
    for step in range(100):  # 0.5 m/s straight, counted in alternate 2 ms and 18 ms steps
        at += 0.002 if step % 2 else 0.018
        if not step % 2:
            left = right = left + 0.5 * 0.02 / 0.0825
        odometry.take(left, right, at)
        speeds.append(odometry.twist.linear)
    assert all(s == pytest.approx(0.5, rel=0.15) for s in speeds[20:]), speeds[20:]
    odometry.reset()
    assert odometry.twist == Twist()


def test_odometry_of_an_arc_stays_on_its_circle_and_measures_its_twist() -> None:
    """A quarter of a circle of 1 m, counter-clockwise at 0.5 m/s, read in 2° steps: each
    step taken at its midpoint heading lands on the circle, and the measured twist is the
    arc's own."""
    odometry, radius = Odometry(GEOMETRY), 1.0
    odometry.take(0.0, 0.0, 0.0)
    step_rad, steps = math.radians(2), 45
    track, wheel = GEOMETRY.track_m, GEOMETRY.wheel_radius_m
    left_step = step_rad * (radius - track / 2) / wheel
    right_step = step_rad * (radius + track / 2) / wheel
    dt = step_rad * radius / 0.5
    for k in range(1, steps + 1):
        odometry.take(k * left_step, k * right_step, k * dt)
    pose = odometry.pose
    chord = 2 * math.sin(step_rad / 2) / step_rad  # each step's chord for its arc's length
    assert pose.theta == pytest.approx(math.pi / 2)
    assert pose.x == pytest.approx(radius / chord, rel=1e-9)
    assert pose.y == pytest.approx(radius / chord, rel=1e-9)
    assert odometry.twist.linear == pytest.approx(0.5)
    assert odometry.twist.angular == pytest.approx(0.5 / radius)


def test_the_measured_twist_is_the_travel_over_the_fewest_last_steps_spanning_its_window():
    odometry = Odometry(GEOMETRY)
    metre = 1 / GEOMETRY.wheel_radius_m  # a wheel's radians for a metre
    odometry.take(0.0, 0.0, 0.0)
    odometry.take(-0.1 * metre, 0.1 * metre, 0.25)  # a first step, on its own: on the spot
    assert odometry.twist == Twist(0.0, pytest.approx(0.2 / GEOMETRY.track_m / 0.25))
    # steps of 1/32 s (exact): the window of 0.1 s is the last four
    at, left = 0.5, 0.0
    odometry.reset()
    odometry.take(left, left, at)
    measured = []
    for speed in [0.2] * 6 + [0.6] * 4:
        at, left = at + 1 / 32, left + speed / 32 * metre
        odometry.take(left, left, at)
        measured.append(odometry.twist.linear)
    assert measured[-5:] == pytest.approx([0.2, 0.3, 0.4, 0.5, 0.6])
    # a window's second step exactly 0.1 s before the last: the window starts there
    odometry.reset()
    odometry.take(0.0, 0.0, -0.05)
    odometry.take(0.05 * metre, 0.05 * metre, 0.0)
    odometry.take(0.05 * metre + 0.03 * metre, 0.05 * metre + 0.03 * metre, 0.1)
    assert odometry.twist.linear == pytest.approx(0.3)


def test_a_drive_finishes_after_two_slots_at_rest_past_its_hold() -> None:
    drive = Drive(GEOMETRY, wheel_joint(1e-3), wheel_joint(-1e-3))
    drive.command(Twist(), now=100.0, hold_s=0.5)  # 0, held until 100.5
    drive.begin(100.0, Twist())
    drive.sample(0.02)
    drive.sample(0.02)  # the other wheel, the same slot: not a slot more
    assert not drive.finished(101.0)
    drive.sample(0.04)
    assert drive.finished(101.0) and not drive.finished(100.5)  # past the hold, not at it
    drive.command(Twist(0.1, 0.0), now=101.0, hold_s=0.01)
    drive.begin(101.0, Twist(0.02, 0.0))  # moving: two slots down to 0 at 0.8 m/s²
    drive.sample(0.02)
    drive.sample(0.04)
    assert drive.sent == Twist()
    assert not drive.finished(102.0)  # one slot at rest since it moved
    drive.sample(0.06)
    assert drive.finished(102.0)
