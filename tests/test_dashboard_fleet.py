"""The dashboard's model of the fleet (``busgate.dashboard.fleet``), fed as zenoh would feed
it, hostile samples included, on a fake clock: what it keeps, what it drops, what a browser
is told and when."""

from __future__ import annotations

import json
import math

import pytest

from busgate.dashboard.fleet import (
    CLOCK_STEP_S,
    EVENTS_KEPT,
    HISTORY_S,
    MAX_BASES,
    MAX_BUSES,
    MAX_DEVICES,
    MAX_GATEWAYS,
    SAMPLE_EVERY_S,
    TRACK_POINTS,
    TRACK_STEP_M,
    Fleet,
)


def info(*devices: str, bus: str = "uart0") -> dict:
    return {"ok": True, "gateway": "gw1", "version": "9.9",
            "buses": [{"name": bus, "protocol": "inspire_la",
                       "devices": [{"name": d, "kind": "inspire_la", "id": i + 1, "state": None}
                                   for i, d in enumerate(devices)]}]}


def state(ts: float, position: float = 0, **fields) -> dict:
    return {"ts": ts, "device": "la1", "kind": "inspire_la", "online": True, "position": position,
            "target": position, "current_ma": 12, **fields}


def up(fleet: Fleet, *devices: str, name: str = "gw1") -> None:
    assert fleet.gateway_up(name)
    fleet.info(name, info(*devices))


def test_a_gateway_is_shown_once_up_with_its_buses_and_devices_and_gone_when_it_goes() -> None:
    fleet = Fleet(clock=lambda: 100.0)
    assert fleet.drain() is None
    up(fleet, "la1", "la2")
    delta = fleet.drain()
    assert delta["now"] == 100.0 and delta["gone"] == []
    [gateway] = delta["gateways"]
    assert gateway["name"] == "gw1" and gateway["version"] == "9.9"
    assert gateway["buses"] == [{"name": "uart0", "protocol": "inspire_la", "stats": None,
                                 "devices": ["la1", "la2"]}]
    assert fleet.drain() is None  # told once
    assert not fleet.gateway_up("gw1")  # already known: no second info asked
    fleet.gateway_gone("gw1")
    assert fleet.drain()["gone"] == ["gw1"]
    assert fleet.snapshot()["gateways"] == [] and not fleet.has("gw1")


def test_nothing_is_taken_for_a_gateway_that_is_not_up_or_a_device_its_info_does_not_list() -> None:
    fleet = Fleet()
    fleet.state("gw1", "la1", state(1.0))
    fleet.info("gw1", info("la1"))
    fleet.event("gw1", {"ts": 1.0, "device": "la1", "type": "online"})
    fleet.stats("gw1", "uart0", {"ts": 1.0, "frames_out": 1, "frames_in": 1})
    assert fleet.drain() is None and fleet.snapshot()["gateways"] == []
    up(fleet, "la1")
    fleet.drain()
    fleet.state("gw1", "ghost", state(2.0))
    fleet.stats("gw1", "nobus", {"ts": 1.0})
    assert fleet.drain() is None
    fleet.gateway_gone("gw1")
    fleet.drain()
    fleet.state("gw1", "la1", state(3.0))  # a sample late after the token went: not brought back
    assert fleet.drain() is None and not fleet.has("gw1")


def test_a_state_is_told_with_the_samples_since_the_last_drain_at_most_one_per_interval() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.drain()
    step = SAMPLE_EVERY_S / 5
    for n in range(10):  # two intervals' worth: the latest of each interval is kept
        fleet.state("gw1", "la1", state(10.0 + n * step, position=n))
    [device] = fleet.drain()["devices"]
    assert device["state"]["position"] == 9
    assert [s[1] for s in device["samples"]] == [4, 9]
    assert device["samples"][0] == [10.0 + 4 * step, 4, 4, 12]
    assert fleet.drain() is None
    fleet.state("gw1", "la1", state(20.0, position=50))
    [device] = fleet.drain()["devices"]
    assert [s[1] for s in device["samples"]] == [50]  # only what is new


def test_a_minute_of_samples_is_kept_and_a_new_browser_gets_it_all() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    for n in range(200):
        fleet.state("gw1", "la1", state(n * 1.0, position=n))
    [device] = fleet.snapshot()["devices"]
    times = [s[0] for s in device["samples"]]
    assert times[0] >= 199 - HISTORY_S and times[-1] == 199.0
    assert len(times) == HISTORY_S + 1


def test_what_is_not_a_finite_number_is_not_plotted_and_no_nan_reaches_a_browser() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.state("gw1", "la1", state(1.0, position=math.nan, target=True, current_ma="12",
                                    temperature_c=math.inf, nested={"x": [-math.inf]}))
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, None, None, None]]
    assert device["state"]["temperature_c"] is None and device["state"]["nested"] == {"x": [None]}
    json.dumps(fleet.snapshot(), allow_nan=False)  # what the hub sends: strict JSON
    fleet.state("gw1", "la1", {"ts": "soon", "position": 3})  # no time: a state, no sample
    assert fleet.drain()["devices"][0]["samples"] == []


def test_malformed_payloads_are_dropped() -> None:
    fleet = Fleet()
    assert fleet.gateway_up("gw1")
    for body in (None, [], "x", 3, {"buses": "no"}, {"buses": [1, {"name": 2}]}):
        fleet.info("gw1", body)
    fleet.info("gw1", {"buses": [{"name": "uart0", "devices": [None, {"name": None}, {}]}]})
    assert fleet.snapshot()["devices"] == []
    up_info = info("la1")
    fleet.info("gw1", up_info)
    for body in (None, [], "x"):
        fleet.state("gw1", "la1", body)
        fleet.stats("gw1", "uart0", body)
        fleet.event("gw1", body)
    assert fleet.snapshot()["events"] == [] and fleet.snapshot()["devices"][0]["state"] is None


def test_frames_per_second_come_from_two_statistics_of_a_bus() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.stats("gw1", "uart0", {"ts": 10.0, "frames_out": 100, "frames_in": 90, "up": True})
    fleet.stats("gw1", "uart0", {"ts": 12.0, "frames_out": 300, "frames_in": 290, "up": True})
    [bus] = fleet.drain()["gateways"][0]["buses"]
    assert bus["frames_per_s"] == 200.0 and bus["stats"]["frames_out"] == 300
    fleet.stats("gw1", "uart0", {"ts": 12.0, "frames_out": "x", "frames_in": 1})
    [bus] = fleet.drain()["gateways"][0]["buses"]
    assert bus["frames_per_s"] is None


def test_events_are_kept_to_a_bound_and_each_told_once() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.drain()
    for n in range(EVENTS_KEPT + 10):
        fleet.event("gw1", {"ts": n, "device": "la1", "type": "claimed"})
    told = fleet.drain()["events"]
    assert len(told) == EVENTS_KEPT and told[-1]["event"]["ts"] == EVENTS_KEPT + 9
    assert told[0] == {"gateway": "gw1", "event": {"ts": 10, "device": "la1", "type": "claimed"}}
    assert fleet.drain() is None and len(fleet.snapshot()["events"]) == EVENTS_KEPT


def test_a_flood_of_gateways_buses_or_devices_is_bounded() -> None:
    fleet = Fleet()
    assert all(fleet.gateway_up(f"gw{n}") for n in range(MAX_GATEWAYS))
    assert not fleet.gateway_up("one-too-many") and fleet.full
    fleet.info("gw0", info(*(f"d{n}" for n in range(MAX_DEVICES + 5))))
    assert sum(d["gateway"] == "gw0" for d in fleet.snapshot()["devices"]) == MAX_DEVICES
    buses = [{"name": f"b{n}", "protocol": "inspire_la", "devices": []} for n in range(40_000)]
    long_name = {"name": "x" * 100_000, "protocol": "inspire_la", "devices": [{"name": "y"}]}
    fleet.info("gw1", {"ok": True, "gateway": "gw1", "buses": [long_name, *buses]})
    [gw1] = [g for g in fleet.snapshot()["gateways"] if g["name"] == "gw1"]
    assert len(gw1["buses"]) == MAX_BUSES and "x" * 200 not in str(gw1)


def test_a_payload_nested_past_any_state_is_cut_not_a_crash() -> None:
    """``json.loads`` takes nesting 999 deep, past the interpreter's stack for a recursive
    reading: one such state raised in zenoh's thread, logged with a 150 KB traceback."""
    fleet = Fleet()
    up(fleet, "la1")
    deep: object = 1
    for _ in range(900):
        deep = {"a": deep}
    fleet.state("gw1", "la1", state(1.0, position=5, deep=deep))
    [la1] = fleet.snapshot()["devices"]
    assert la1["state"]["position"] == 5


def test_a_state_from_before_a_clock_set_back_starts_the_plot_again() -> None:
    """One state stamped an hour ahead (a peer's put, a clock set back) left every later
    sample replacing the last for an hour: the plot held one point."""
    fleet = Fleet()
    up(fleet, "la1")
    fleet.state("gw1", "la1", state(100.0 + 3600, position=1))
    [told] = fleet.drain()["devices"]  # an open browser has it
    assert not told["restart"] and len(told["samples"]) == 1
    for n in range(20):
        fleet.state("gw1", "la1", state(100.0 + n * SAMPLE_EVERY_S * 2, position=n))
    [la1] = fleet.snapshot()["devices"]
    assert len(la1["samples"]) == 20 and la1["restart"]  # a new browser's first message
    [told] = fleet.drain()["devices"]  # and the open browser drops the hour-ahead one
    assert told["restart"] and len(told["samples"]) == 20
    last = 100.0 + 20 * SAMPLE_EVERY_S * 2
    fleet.state("gw1", "la1", state(last, position=20))
    assert not fleet.drain()["devices"][0]["restart"]
    fleet.state("gw1", "la1", state(last - CLOCK_STEP_S / 2, position=99))  # jitter: kept
    assert len(fleet.snapshot()["devices"][0]["samples"]) == 21


# -- joints ------------------------------------------------------------------------------------

def with_joint(joint: dict | None, kind: str = "inspire_la", device: str = "la1") -> dict:
    entry = {"name": device, "kind": kind, "id": 1, "state": None}
    return {"ok": True, "gateway": "gw1", "version": "9.9", "buses": [
        {"name": "uart0", "protocol": kind,
         "devices": [entry if joint is None else {**entry, "joint": joint}]}]}


def joint_state(ts: float, **joint) -> dict:
    return state(ts, position=1000, target=1200, joint={
        "name": "lift", "type": "position", "unit": "m", "position": 0.011, "velocity": None,
        "effort": 0.5, "target": 0.013, **joint})


def described(joint: dict | None, kind: str = "inspire_la", device: str = "la1") -> Fleet:
    fleet = Fleet()
    assert fleet.gateway_up("gw1")
    fleet.info("gw1", with_joint(joint, kind, device))
    fleet.drain()
    return fleet


def test_a_position_joint_is_plotted_and_told_in_si_with_its_target() -> None:
    fleet = described(None)
    fleet.state("gw1", "la1", joint_state(1.0))
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, 0.011, 0.013, 12]]
    assert device["joint"] == {
        "name": "lift", "type": "position", "value": 0.011, "value_unit": "m",
        "target": 0.013, "velocity": None, "velocity_unit": "m/s",
        "effort": 0.5, "effort_unit": "N"}
    assert device["state"]["position"] == 1000  # the raw values, as they came


def test_a_velocity_joint_is_plotted_by_its_velocity_and_its_target_velocity() -> None:
    fleet = described(None, kind="zlac706", device="wheel")
    fleet.state("gw1", "wheel", {"ts": 1.0, "kind": "zlac706", "speed_rpm": 59.0,
                                 "target_speed_rpm": 60.0, "current_ma": 300, "joint": {
                                     "name": "wheel", "type": "velocity", "unit": "rad",
                                     "position": 3.0, "velocity": 6.18, "effort": 0.3,
                                     "target": 2 * math.pi}})
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, 6.18, pytest.approx(2 * math.pi), 300]]
    told = device["joint"]
    assert (told["value"], told["value_unit"], told["velocity_unit"]) == (6.18, "rad/s", "rad/s")


def test_a_joint_in_raw_units_is_plotted_as_it_came() -> None:
    fleet = described(None)
    fleet.state("gw1", "la1", joint_state(1.0, name="la1", unit="raw", position=1000.0,
                                          target=1200.0))
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, 1000.0, 1200.0, 12]]


def test_a_state_without_a_joint_is_plotted_raw_and_told_without_one() -> None:
    fleet = described(None)  # a gateway of an earlier release
    fleet.state("gw1", "la1", state(1.0, position=700, target=800))
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, 700, 800, 12]] and device["joint"] is None
    wheel = described(None, kind="zlac706", device="wheel")  # a velocity joint unless told
    wheel.state("gw1", "wheel", {"ts": 1.0, "position": 5, "speed_rpm": 30.0,
                                 "target_speed_rpm": 40.0})
    assert wheel.drain()["devices"][0]["samples"] == [[1.0, 30.0, 40.0, None]]


@pytest.mark.parametrize("joint", [
    {"target": None}, {"target": "0.013"}, {"target": math.nan}, {"target": math.inf},
    {"target": True}, {"target": [0.013]}, {"type": "sideways", "target": None},
    {"type": 3, "target": None},
], ids=["none", "text", "nan", "inf", "bool", "list", "type", "type not text"])
def test_a_malformed_target_leaves_the_target_unknown_never_the_page(joint) -> None:
    fleet = described(None)
    fleet.state("gw1", "la1", joint_state(1.0, **joint))
    [device] = fleet.drain()["devices"]
    assert device["samples"] == [[1.0, 0.011, None, 12]]  # its value from its state still
    assert device["joint"]["value"] == 0.011 and device["joint"]["target"] is None
    assert device["joint"]["type"] == "position"  # an LA's, whatever the state says
    json.dumps(fleet.snapshot(), allow_nan=False)


@pytest.mark.parametrize("values", [
    "not an object", {"position": "0.011"}, {"position": math.inf}, {"position": True},
    {"name": ["x"], "unit": {"m": 1}}, {"unit": "m" * 1000, "name": "n" * 1000},
], ids=["not an object", "text", "inf", "bool", "not text", "long"])
def test_a_malformed_joint_in_a_state_is_shown_as_nothing_known(values) -> None:
    fleet = described(None)
    joint = values if isinstance(values, str) else {"position": 0.01, **values}
    fleet.state("gw1", "la1", state(1.0, joint=joint))
    [device] = fleet.drain()["devices"]
    told = device["joint"]
    if isinstance(values, str):
        assert told is None and device["samples"] == [[1.0, 0, 0, 12]]  # plotted raw
    else:
        assert told["value"] in (None, 0.01) and told["target"] is None
        assert told["name"] is None or len(told["name"]) <= 64
        assert len(told["value_unit"]) <= 16
    json.dumps(fleet.snapshot(), allow_nan=False)


# -- bases -------------------------------------------------------------------------------------

def odometry(ts: float, x: float = 0.0, y: float = 0.0, theta: float = 0.0, **fields) -> dict:
    return {"base": "base", "ts": ts, "x": x, "y": y, "theta": theta, "linear": 0.25,
            "angular": -0.5, "commanded": {"linear": 0.3, "angular": -0.5}, **fields}


def test_a_base_appears_with_its_first_odometry_and_goes_with_its_gateway() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.drain()
    assert fleet.snapshot()["bases"] == []  # info lists none: its odometry tells
    fleet.odometry("gw1", "base", odometry(1.0, x=0.5, y=0.25, theta=1.0))
    [base] = fleet.drain()["bases"]
    assert base == {"gateway": "gw1", "base": "base", "restart": False,
                    "odometry": odometry(1.0, x=0.5, y=0.25, theta=1.0),
                    "measured": {"linear": 0.25, "angular": -0.5},  # its own, at first
                    "track": [[1.0, 0.5, 0.25]]}
    fleet.odometry("gw1", "base", odometry(1.1, x=0.5 + TRACK_STEP_M / 2, y=0.25))
    [base] = fleet.drain()["bases"]  # told, not tracked: it moved under a step
    assert base["odometry"]["x"] == 0.5 + TRACK_STEP_M / 2 and base["track"] == []
    fleet.odometry("gw1", "base", odometry(1.2, x=0.52, y=0.25))
    assert fleet.drain()["bases"][0]["track"] == [[1.2, 0.52, 0.25]]
    assert fleet.drain() is None
    [base] = fleet.snapshot()["bases"]  # a new browser: all of it, to start its track from
    assert base["track"] == [[1.0, 0.5, 0.25], [1.2, 0.52, 0.25]] and base["restart"]
    fleet.odometry("gw1", "base", odometry(1.3, x=0.53, y=0.25))
    fleet.gateway_gone("gw1")
    assert fleet.drain()["bases"] == [] and fleet.snapshot()["bases"] == []
    fleet.odometry("gw1", "base", odometry(1.4))  # late, after the token went: not brought back
    assert fleet.drain() is None


def test_a_track_stays_bounded_and_a_base_at_rest_adds_nothing_to_it() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    for n in range(3 * TRACK_POINTS):  # 2 cm every 100 ms, round a circle of 1 m radius
        angle = n * 0.02
        fleet.odometry("gw1", "base", odometry(n * 0.1, x=math.sin(angle), y=1 - math.cos(angle),
                                               theta=angle))
    [told] = fleet.drain()["bases"]
    assert len(told["track"]) == TRACK_POINTS  # what the browsers had not had: bounded too
    track = fleet.snapshot()["bases"][0]["track"]
    assert len(track) == TRACK_POINTS
    assert track[-1][0] == pytest.approx((3 * TRACK_POINTS - 1) * 0.1)
    assert [p[0] for p in track] == sorted(p[0] for p in track)
    last = track[-1]
    for n in range(100):  # at rest, the odometry still told
        fleet.odometry("gw1", "base", odometry(1000.0 + n * 0.1, x=last[1], y=last[2]))
    assert fleet.snapshot()["bases"][0]["track"] == track
    assert fleet.drain()["bases"][0]["odometry"]["ts"] == pytest.approx(1009.9)


def test_a_pose_that_jumps_starts_the_track_again() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    for n in range(20):  # 0.25 m/s, as measured
        fleet.odometry("gw1", "base", odometry(n * 0.1, x=n * 0.025))
    fleet.drain()
    fleet.odometry("gw1", "base", odometry(2.0, x=0.5))
    fleet.odometry("gw1", "base", odometry(2.1))  # reset_odometry: back at 0 in 100 ms
    fleet.odometry("gw1", "base", odometry(2.2, x=0.025))
    [base] = fleet.drain()["bases"]
    assert base["restart"] and base["track"] == [[2.1, 0.0, 0.0], [2.2, 0.025, 0.0]]
    assert fleet.snapshot()["bases"][0]["track"] == base["track"]
    fleet.odometry("gw1", "base", odometry(12.2, x=2.5))  # 10 s later: a slow publisher
    fleet.odometry("gw1", "base", odometry(12.3, x=9.0, linear=math.nan))  # speed unknown
    [base] = fleet.drain()["bases"]
    assert not base["restart"] and base["track"] == [[12.2, 2.5, 0.0], [12.3, 9.0, 0.0]]


def test_the_measured_twist_is_the_odometrys_own() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.odometry("gw1", "base", odometry(1.0, x=0.1, linear=0.3, angular=-0.2))
    assert fleet.drain()["bases"][0]["measured"] == {"linear": 0.3, "angular": -0.2}


@pytest.mark.parametrize("body", [
    None, [], "x", 3, {}, odometry(1.0, x="1"), {**odometry(1.0), "ts": True},
    odometry(1.0, commanded={"linear": 0.3}), odometry(1.0, extra=1),
    odometry(1.0, base="other"), odometry(1.0, base="<b>"),
    {k: v for k, v in odometry(1.0).items() if k != "commanded"},
], ids=["none", "list", "text", "number", "empty", "x text", "ts bool", "half commanded",
        "extra", "another base", "not a name", "no commanded"])
def test_what_is_not_an_odometry_of_the_base_its_key_names_is_dropped(body) -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.drain()
    fleet.odometry("gw1", "base", body)
    assert fleet.drain() is None and fleet.snapshot()["bases"] == []


def test_a_non_finite_pose_is_told_as_unknown_and_not_tracked_and_bases_are_bounded() -> None:
    fleet = Fleet()
    up(fleet, "la1")
    fleet.odometry("gw1", "base", odometry(1.0, x=math.nan, theta=math.inf))
    [base] = fleet.drain()["bases"]
    assert base["odometry"]["x"] is None and base["odometry"]["theta"] is None
    assert base["track"] == []
    json.dumps(fleet.snapshot(), allow_nan=False)
    for n in range(MAX_BASES + 5):
        name = f"b{n}"
        fleet.odometry("gw1", name, odometry(1.0, base=name))
    assert len(fleet.snapshot()["bases"]) == MAX_BASES
