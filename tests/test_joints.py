"""Joints without a bus: SI conversions, limits, the config's checks, the follow limiter on a
tick count, and the joints message's timing on a fake clock."""

from __future__ import annotations

import math
import re
from itertools import pairwise

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.errors import ConfigError, RefusedError
from busgate.gateway.api.joints import JointsFeed
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.recording.mcap_log import REPLAYED_LEAVES, schema_name
from busgate.gateway.scheduler.limiter import StreamLimiter
from busgate.schemas import ds_servo, inspire_la, zlac706
from busgate.schemas.config import ignored_keys, parse_config
from busgate.schemas.joints import Joint, JointTable, published, table_warnings

TURN = 2 * math.pi


def la_joint(**table) -> Joint:
    return Joint.of("la1", inspire_la.JOINT, JointTable(**{"unit": "m", "scale": 5e-6, **table}))


def wheel(**table) -> Joint:
    defaults = {"unit": "rad", "scale": TURN / 10_000}
    return Joint.of("wheel", zlac706.JOINT, JointTable(**{**defaults, **table}))


# -- conversions -----------------------------------------------------------------------------------

scales = st.floats(min_value=1e-7, max_value=10).flatmap(
    lambda s: st.sampled_from([s, -s])
)


@given(scale=scales, offset=st.floats(-10, 10), raw=st.integers(0, 2000))
def test_a_raw_position_comes_back_from_si(scale, offset, raw):
    joint = la_joint(scale=scale, offset=offset)
    assert joint.target_raw(joint.position_si(raw)) == raw


@given(scale=scales, offset=st.floats(-10, 10), raw=st.integers(0, 2000))
def test_a_published_position_still_names_its_count(scale, offset, raw):
    """Rule 5: the published value loses float noise, never a count."""
    joint = la_joint(scale=scale, offset=offset)
    assert joint.target_raw(joint.state({"position": raw})["position"]) == raw


def test_a_published_value_has_no_float_noise_in_its_last_digits():
    """The demo's ``la1`` at 1500 was answered 0.007500000000000001 m (rule 5)."""
    state = la_joint().state({"position": 1500, "target": 1500, "force_g": 300})
    assert (state["position"], state["target"]) == (0.0075, 0.0075)
    assert published(0.1 + 0.2) == 0.3 and published(-3.0000000000000004) == -3.0
    assert published(math.pi) == 3.14159265358979  # 15 significant digits
    assert published(0.0) == 0.0 and math.isnan(published(math.nan))


@given(scale=scales, offset=st.floats(-1, 1), fraction=st.floats(0, 1))
def test_an_si_target_inside_the_limits_never_rounds_past_them(scale, offset, fraction):
    ends = sorted(offset + scale * raw for raw in (0, 2000))
    low, high = ends[0] + (ends[1] - ends[0]) * 0.25, ends[0] + (ends[1] - ends[0]) * 0.75
    joint = la_joint(scale=scale, offset=offset, min=low, max=high)
    raw = joint.target_raw(low + (high - low) * fraction)
    lowest, highest = joint.raw_limits
    assert lowest <= raw <= highest
    slack = 1e-9 * max(1, abs(low), abs(high))
    assert low - slack <= joint.position_si(raw) <= high + slack


@given(rpm=st.floats(-1000, 1000), turn=st.floats(100, 1e6), flip=st.booleans())
def test_a_speed_comes_back_from_si(rpm, turn, flip):
    joint = wheel(scale=(-1 if flip else 1) * TURN / turn, raw_per_turn=turn)
    assert joint.speed_of(joint.velocity_si(rpm)) == pytest.approx(rpm, abs=1e-9)


def test_rpm_to_rad_per_s_is_exact_with_the_manuals_pulses_per_turn():
    assert wheel().velocity_si(60.0) == pytest.approx(TURN, rel=1e-15)
    assert wheel(scale=-TURN / 10_000).velocity_si(60.0) == pytest.approx(-TURN, rel=1e-15)
    # A velocity joint's target is its commanded speed, in SI.
    state = wheel().state({"target_speed_rpm": 60.0, "speed_rpm": 30.0, "target": 5})
    assert (state["type"], state["target"]) == ("velocity", pytest.approx(TURN))


def test_the_joint_state_is_in_si_with_the_direction_of_the_scale():
    joint = la_joint(scale=-5e-6, offset=0.01)
    state = joint.state({"position": 1000, "force_g": 1000})
    assert state == {"name": "la1", "type": "position", "unit": "m",
                     "position": pytest.approx(0.005), "velocity": None,
                     "effort": pytest.approx(-9.80665), "target": None}
    assert joint.state({"position": None, "force_g": None})["position"] is None
    assert joint.state({"target": 200})["target"] == pytest.approx(0.009)


def test_a_device_without_a_table_is_a_raw_joint_limited_by_its_range():
    joint = Joint.of("s1", ds_servo.JOINT, None)
    assert (joint.unit, joint.scale, joint.raw_limits) == ("raw", 1.0, (0, 4095))
    assert not joint.limited
    assert joint.target_raw(4095) == 4095
    joint.check_position(None)  # a preset: nothing to hold it within
    with pytest.raises(RefusedError, match="max 4095 raw"):
        joint.target_raw(4096)


# -- limits ----------------------------------------------------------------------------------------


def test_a_refusal_names_the_joint_the_limit_and_the_value():
    joint = la_joint(name="gripper_left", min=0.001, max=0.008)
    message = "joint gripper_left: position 0.0085 m is beyond its max 0.008 m"
    with pytest.raises(RefusedError, match=re.escape(message)):
        joint.check_position(1700)
    with pytest.raises(RefusedError, match=re.escape("beyond its min 0.001 m")) as refused:
        joint.target_raw(0.0005)
    assert refused.value.code == "out_of_range"
    with pytest.raises(RefusedError, match="cannot know"):
        joint.check_position(None)  # a limited joint refuses a target it cannot check
    with pytest.raises(RefusedError) as refused:  # past it by less than six digits show
        joint.target_raw(0.0080001)
    assert str(refused.value).endswith("position 0.0080001 m is beyond its max 0.008 m")
    with pytest.raises(RefusedError) as refused:  # not "-0" (an audit's)
        joint.target_raw(-0.0)
    assert str(refused.value).endswith("position 0 m is beyond its min 0.001 m")
    below_zero = la_joint(name="g", offset=-0.005, min=-0.002, max=0.002)
    with pytest.raises(RefusedError) as refused:  # a negative limit too (a review's)
        below_zero.target_raw(-0.002000004)
    assert str(refused.value).endswith("position -0.002000004 m is beyond its min -0.002 m")
    # past it by a hair, as a conversion leaves it: to the digits a double keeps, not repr's
    fast = wheel(max_velocity=15.0)
    with pytest.raises(RefusedError) as refused:
        fast.check("velocity", fast.speed_of(15.0000001))
    assert str(refused.value).endswith("velocity 15.0000001 rad/s is beyond its max_velocity "
                                       "15 rad/s"), refused.value


def test_velocity_and_effort_limits():
    joint = wheel(max_velocity=TURN, max_effort=5.0)
    joint.check("velocity", 60.0)
    message = "velocity -6.9115 rad/s is beyond its max_velocity 6.28319 rad/s"
    with pytest.raises(RefusedError, match=re.escape(message)):
        joint.check("velocity", -66.0)
    joint.check("effort", -5.0)
    with pytest.raises(RefusedError, match=re.escape("effort 5.5 A is beyond its max_effort 5 A")):
        joint.check("effort", 5.5)
    # A speed the gateway cannot know (a ZLAC706's move before its top speed was set).
    with pytest.raises(RefusedError, match=re.escape("cannot know (a top speed not set), so it "
                                                     "cannot keep the joint within its "
                                                     "max_velocity 6.28319 rad/s")):
        joint.check("velocity", None)
    wheel().check("velocity", None)  # without max_velocity: the drive's own range's to keep
    with pytest.raises(RefusedError) as refused:  # below by less than six digits show: all
        joint.check("effort", -5.0000001)
    assert "effort -5.0000001 A is beyond" in str(refused.value)


def test_commands_in_si_become_the_kinds_own():
    assert la_joint(max=0.008).move_command(0.005) == {"op": "move", "position": 1000}
    assert wheel().turn_command(TURN) == {"op": "velocity", "rpm": pytest.approx(60.0)}
    with pytest.raises(RefusedError, match="velocity joint"):
        wheel().move_command(1.0)
    with pytest.raises(RefusedError, match="position joint"):
        la_joint().turn_command(1.0)
    with pytest.raises(RefusedError, match="max_velocity"):
        wheel(max_velocity=1.0).turn_command(2.0)


def test_a_joints_follow_targets_in_si_are_its_types_where_its_family_streams_both():
    """A ZLAC706 streams speeds (velocity mode) or positions (position mode): its joint's SI
    follow target is its type's, and the other is refused; an LA streams positions."""
    assert wheel().follows == "velocity" and wheel(type="position").follows == "position"
    assert wheel(type="position").kind_follow(TURN, None) == ({"position": 10_000}, 10_000)
    assert wheel().kind_follow(None, TURN) == ({"rpm": pytest.approx(60.0)}, pytest.approx(60))
    with pytest.raises(RefusedError, match="follows speeds: send joint_velocity"):
        wheel().kind_follow(TURN, None)
    with pytest.raises(RefusedError, match="follows positions: send joint,"):
        wheel(type="position").kind_follow(None, TURN)
    assert la_joint(type="position").follows == "position"


def config_with(joint: dict | None, kind: str = "inspire_la") -> dict:
    return {"gateway": {"name": "g"}, "buses": [{
        "name": "b", "transport": "serial", "port": "/dev/null", "baudrate": 921600,
        "devices": [{"name": "d1", "kind": kind, "id": 1, "joint": joint}]}]}


@pytest.mark.parametrize(("joint", "path", "words"), [
    ({"unit": "m", "scale": 0.0}, "joint.scale", "not 0"),
    ({"unit": "m", "scale": -1e-300}, "joint.scale", "at least 1e-12 in size"),
    ({"unit": "m", "scale": 1e-5, "min": 0.01, "max": 0.005}, "joint.min", "below max"),
    ({"unit": "m", "scale": 1e-5, "max": 0.05}, "joint.max", "outside the device's range 0–0.02"),
    ({"unit": "m", "scale": 1e-5, "type": "velocity"}, "joint.type", "must be one of position"),
    ({"unit": "m", "scale": 1e-5, "raw_per_turn": 10}, "joint.raw_per_turn", "not a rotary"),
    ({"unit": "furlong", "scale": 1e-5}, "joint.unit", "'m' or 'rad'"),
    ({"unit": "m", "scale": 1e-5, "max_velocity": -1.0}, "joint.max_velocity", "greater than 0"),
    ({"unit": "m", "scale": 1e-5, "maxx": 1.0}, "joint", "did you mean `max`"),
    # min and max within one count (5 µm): a target between them rounded outside them
    ({"unit": "m", "scale": 5e-6, "min": 0.0050001, "max": 0.0050004}, "joint.min",
     "0.0050001–0.0050004 m holds no whole count of the device"),
    # an audit's: near a large offset a limit past the stroke was taken (at 1e8 m, 0.05 m
    # past it; here a tenth of a count past it at 1000 m)...
    ({"unit": "m", "scale": 5e-6, "offset": 1000.0, "max": 1000.0100005}, "joint.max",
     "outside the device's range"),
    # ... and a calibration whose counts a double cannot tell apart (every target raw 0)
    ({"unit": "m", "scale": 1e-12, "offset": 1e9}, "joint.offset",
     r"1e\+09 m leaves no count of 1e-12 m told apart near 1e\+09 m"),
])
def test_the_config_refuses_a_joint_table_naming_the_key(joint, path, words):
    with pytest.raises(ConfigError, match=words) as refused:
        parse_config(config_with(joint))
    assert f"devices[0].{path}" in str(refused.value)


@pytest.mark.parametrize("key", ["min", "max"])
def test_min_and_max_of_a_velocity_joint_are_refused(key):
    """An outside audit: taken, they showed in ``info`` as limits nothing kept (a wheel turns
    on without end); a position joint of the same table takes them."""
    table = {"unit": "rad", "scale": TURN / 10_000, key: 1.0 if key == "max" else -1.0}
    with pytest.raises(ConfigError, match='velocity joint turns on without end: give the joint '
                                          'type = "position"') as refused:
        parse_config(config_with(table, kind="zlac706"))
    assert f"devices[0].joint.{key}" in str(refused.value)
    parse_config(config_with({**table, "type": "position"}, kind="zlac706"))


def test_whole_count_limits_stay_within_the_limits_however_large_the_counts():
    """An audit: at 1.5e9 counts the relative slack was 1.5 counts, and a max 0.4 count past
    a whole one took the next count, past max."""
    table = {"unit": "m", "scale": 1e-3, "type": "position", "max": 1_500_000.0004}
    config = parse_config(config_with(table, kind="zlac706"))
    joint = Joint.of("d1", zlac706.JOINT, config.buses[0].devices[0].joint)
    assert joint.raw_limits[1] == 1_500_000_000
    with pytest.raises(RefusedError):
        joint.check_position(1_500_000_001)


def test_issue_26s_example_table_is_taken_and_its_max_effort_where_nothing_sets_one_ignored():
    example = {"name": "gripper_left", "unit": "m", "scale": 5.0e-6, "offset": 0.0, "min": 0.0,
               "max": 0.010, "max_velocity": 0.02, "max_acceleration": 0.5, "max_effort": 20.0}
    config = parse_config(config_with(example))
    assert ignored_keys(config) == [
        "buses[0].devices[0].joint.max_effort: d1: 20 N is ignored: no command of this kind "
        "sets an effort, so there is none to bound (docs/joints.md)"]
    joint = Joint.of("d1", inspire_la.JOINT, config.buses[0].devices[0].joint)
    assert (joint.max, joint.max_effort) == (0.010, None), "info shows no limit it does not keep"
    wheel_table = JointTable(unit="rad", scale=1e-3, max_effort=3.0)
    assert table_warnings(zlac706.JOINT, wheel_table) == [], "a torque command sets one"
    assert Joint.of("w", zlac706.JOINT, wheel_table).max_effort == 3.0


@pytest.mark.parametrize("kind", ["inspire_la", "zlac706"])
def test_a_heartbeat_interval_off_can_is_warned_of_as_ignored(kind):
    """Only a device on CAN sends heartbeats (its driver alone is given the interval): an LA's
    or an RS232 ZLAC706's ``heartbeat_ms`` was taken and ignored in silence."""
    data = config_with(None, kind=kind)
    data["buses"][0]["devices"][0]["heartbeat_ms"] = 100
    assert ignored_keys(parse_config(data)) == [
        "buses[0].devices[0].heartbeat_ms: d1: 100 ms is ignored: only a device on a CAN bus "
        "sends heartbeats, and this one is on a serial bus"]
    data["buses"][0]["devices"][0]["heartbeat_ms"] = 0  # the default: none
    assert ignored_keys(parse_config(data)) == []


def test_joint_names_are_unique_and_never_another_devices_name():
    data = config_with({"unit": "m", "scale": 1e-5, "name": "d2"})
    data["buses"][0]["devices"].append({"name": "d2", "kind": "inspire_la", "id": 2})
    with pytest.raises(ConfigError, match="'d2' already names device 'd2'"):
        parse_config(data)
    data["buses"][0]["devices"][1]["joint"] = {"unit": "m", "scale": 1e-5, "name": "d2"}
    data["buses"][0]["devices"][0]["joint"]["name"] = "same"
    data["buses"][0]["devices"][1]["joint"]["name"] = "same"
    with pytest.raises(ConfigError, match="'same' already names the joint of 'd1'"):
        parse_config(data)


# -- the follow limiter, tick by tick -------------------------------------------------------------


def ticks(limiter: StreamLimiter, wanted: float, count: int) -> list[tuple[float, str | None]]:
    return [limiter.step(wanted) for _ in range(count)]


def test_a_position_step_becomes_a_ramp_at_max_velocity():
    joint = la_joint(max_velocity=0.01)  # 2000 counts a second: 40 a 20 ms tick
    limiter = StreamLimiter(joint, 0.02, start=0)
    sent = ticks(limiter, 1000, 30)
    values = [value for value, _ in sent]
    assert values[:3] == [40, 80, 120] and values[24] == 1000 and values[-1] == 1000
    assert all(b - a <= 40 for a, b in zip([0, *values], values, strict=False))
    assert {limit for _, limit in sent[:24]} == {"max_velocity"} and sent[-1][1] is None


def test_a_position_step_with_max_acceleration_speeds_up_and_brakes_without_overshoot():
    joint = la_joint(max_velocity=0.01, max_acceleration=0.1)  # 20000 counts/s²
    limiter = StreamLimiter(joint, 0.02, start=0)
    values = [value for value, _ in ticks(limiter, 1000, 80)]
    steps = [b - a for a, b in zip([0, *values], values, strict=False)]
    assert max(steps) <= 40 and steps[0] <= 8 + 1  # 20000 × 0.02² = 8 counts more each tick
    assert all(abs(b - a) <= 8 + 2 for a, b in pairwise(steps))  # counts are whole
    assert max(values) == 1000 and values[-1] == 1000


def test_a_stream_from_outside_the_limits_sends_the_nearest_limit_then_ramps():
    """Rule 1: a device resting below ``min`` (raw 400) gets the limit first, never a target
    beyond it to ramp in; from there, 40 counts a tick."""
    joint = la_joint(min=0.002, max=0.008, max_velocity=0.01)
    limiter = StreamLimiter(joint, 0.02, start=0)
    assert [value for value, _ in ticks(limiter, 1000, 3)] == [400, 440, 480]


def test_a_target_past_a_limit_is_clamped_to_it_whatever_the_scales_sign():
    joint = la_joint(scale=-5e-6, offset=0.01, min=0.002)  # min 0.002 m is raw 1600
    limiter = StreamLimiter(joint, 0.02, start=1000)
    assert limiter.step(1900) == (1600, "min")
    assert limiter.step(1500) == (1500, None)
    assert StreamLimiter(joint, 0.02, start=1000).step(-5) == (0, "max")


def test_a_velocity_step_becomes_a_ramp_at_max_acceleration():
    joint = wheel(max_velocity=4 * TURN, max_acceleration=TURN)  # 240 rpm, 60 rpm/s
    limiter = StreamLimiter(joint, 0.02, start=0.0)
    sent = ticks(limiter, 1000.0, 250)
    values = [value for value, _ in sent]
    assert values[0] == pytest.approx(1.2) and values[99] == pytest.approx(120.0)
    assert max(values) == pytest.approx(240.0) and sent[0][1] == "max_velocity"
    assert all(b - a <= 1.2 + 1e-9 for a, b in pairwise(values))
    assert StreamLimiter(joint, 0.02, start=200.0).step(-50.0)[0] == pytest.approx(198.8)


def test_without_limits_a_stream_sends_what_it_is_sent():
    limiter = StreamLimiter(Joint.of("la1", inspire_la.JOINT, None), 0.02, start=0)
    assert ticks(limiter, 2000, 2) == [(2000, None), (2000, None)]
    speeds = StreamLimiter(Joint.of("w", zlac706.JOINT, None), 0.02, start=None)
    assert speeds.step(5000.0) == (1000, "max_velocity")  # the device's top speed


def test_an_unknown_start_takes_the_first_target():
    limiter = StreamLimiter(la_joint(max_velocity=0.01), 0.02, start=None)
    assert limiter.step(1500) == (1500, None)
    assert limiter.step(0) == (1460, "max_velocity")


# -- the joints message ----------------------------------------------------------------------------


def test_the_joints_message_goes_when_a_joint_was_read_again_at_most_at_the_poll_rate():
    drivers = [InspireLaDriver("la1", 1, joint=la_joint()), Zlac706CanDriver("w", 5)]
    feed = JointsFeed("gw", drivers, min_interval_s=0.1)
    assert feed.due(0.0, 100.0) is None  # nothing read yet
    joint = {"position": 0.005, "velocity": None, "effort": 0.1}
    state = {"ts": 1.0, "stale": False, "joint": joint}
    feed.take("la1", state)
    message = feed.due(0.0, 100.0)
    assert message is not None and message["gateway"] == "gw" and message["ts"] == 100.0
    la1, w = message["joints"]
    assert la1 == {"name": "la1", "device": "la1", "type": "position", "unit": "m",
                   "position": 0.005, "velocity": None, "effort": 0.1, "ts": 1.0, "stale": False}
    assert w["ts"] is None and w["stale"] and w["type"] == "velocity" and w["unit"] == "raw"
    feed.take("la1", state)  # the same reading again: no news
    assert feed.due(1.0, 101.0) is None
    feed.take("la1", {**state, "ts": 2.0})
    assert feed.due(1.05, 101.05) is not None
    feed.take("la1", {**state, "ts": 3.0})
    assert feed.due(1.1, 101.1) is None  # within the interval: it waits
    assert feed.due(1.16, 101.16)["joints"][0]["ts"] == 3.0
    feed.take("la1", {"ts": 4.0, "joint": "not an object"})  # distrusted, ignored
    assert feed.due(5.0, 105.0) is None


def test_a_recording_gives_the_joints_key_its_schema_and_replays_it():
    assert schema_name("busgate/gw/joints", "busgate", {}) == "joints.json"
    assert schema_name("busgate/gw/joints/x", "busgate", {}) is None
    assert "joints" in REPLAYED_LEAVES
