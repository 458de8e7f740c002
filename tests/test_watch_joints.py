"""``busgate watch``'s table (``busgate.gateway.cli.watch_table``) shows each device's joint in
SI with its unit beside its raw values, fed plain dicts as zenoh's callbacks would: a position
joint's position, a velocity joint's velocity (its type its state's, else its family's), the
raw values through the family's joint declaration, and a joint missing or malformed as ``-``."""

from __future__ import annotations

import math

import pytest

from busgate.gateway.cli.watch_table import DEVICE_COLUMNS, WatchTable

JOINT = DEVICE_COLUMNS.index("joint")
MOTION = DEVICE_COLUMNS.index("motion")


def la_state(**joint) -> dict:
    state = {"kind": "inspire_la", "online": True, "position": 510, "target": 600,
             "current_ma": 50, "faults": []}
    return state if joint.get("absent") else {**state, "joint": {
        "name": "la1", "unit": "m", "position": 0.0051, "velocity": None, "effort": 0.1,
        **joint}}


def wheel_state(**joint) -> dict:
    return {"kind": "zlac706", "online": True, "mode": "velocity", "position": 1234,
            "target": None, "speed_rpm": 15.0, "target_speed_rpm": 15.0, "current_ma": 300,
            "faults": [], "joint": {"name": "wheel", "unit": "rad", "position": 0.7757,
                                    "velocity": 1.5707963, "effort": 0.3, **joint}}


def cells(table: WatchTable, device: str) -> list[str]:
    line = next(line for line in table.render(1.0) if line.startswith(device))
    return [cell for cell in line.split("  ") if cell]


def row(state: dict, device: str = "la1") -> list[str]:
    table = WatchTable()
    table.update_state(f"busgate/gw1/dev/{device}/state", state, 1.0)
    return cells(table, device)


def test_a_position_joint_shows_its_position_in_si_beside_the_raw_values() -> None:
    shown = row(la_state())
    assert shown[JOINT] == "0.0051 m" and shown[MOTION] == "510 -> 600"
    assert row(la_state(name="lift"))[JOINT] == "lift: 0.0051 m"  # a name not the device's
    assert row(la_state(position=None))[JOINT] == "-"  # never read


def test_a_velocity_joint_shows_its_velocity_per_second_and_its_speed_raw() -> None:
    shown = row(wheel_state(), "wheel")
    assert shown[JOINT] == "1.571 rad/s"  # a ZLAC706 is a velocity joint unless told
    assert row(wheel_state(type="velocity"), "wheel")[JOINT] == "1.571 rad/s"
    assert shown[MOTION] == "15.0 rpm -> 15.0"


def test_the_joints_type_is_its_states_when_told() -> None:
    shown = row(wheel_state(type="position"), "wheel")
    assert shown[JOINT] == "0.7757 rad" and shown[MOTION] == "1234"
    table = WatchTable()
    for _ in range(2):
        table.update_state("busgate/gw1/dev/wheel/state", wheel_state(type="position"), 1.0)
    assert cells(table, "wheel")[JOINT] == "0.7757 rad"
    assert table.changed_lines(1.0)[0].split()[JOINT + 1] == "joint=0.7757rad"
    assert row(wheel_state(type="sideways"), "wheel")[JOINT] == "1.571 rad/s"  # distrusted


@pytest.mark.parametrize("joint", [
    {"absent": True}, {"unit": None}, {"unit": 3}, {"position": "0.1"}, {"position": math.nan},
    {"position": True},
], ids=["absent", "no unit", "unit not text", "text", "nan", "bool"])
def test_a_joint_missing_or_malformed_is_a_dash_and_the_rest_is_shown(joint) -> None:
    shown = row(la_state(**joint))
    assert shown[JOINT] == "-" and shown[MOTION] == "510 -> 600"


def test_a_joint_that_is_not_an_object_or_a_kind_no_family_has_shows_nothing_raw() -> None:
    assert row({**la_state(), "joint": [1, 2]})[JOINT] == "-"
    shown = row({**la_state(), "kind": "warp_drive"})
    assert shown[JOINT] == "0.0051 m" and shown[MOTION] == "-"


@pytest.mark.parametrize(("value", "text"), [
    (0, "0"), (0.0051, "0.0051"), (1.5707963, "1.571"), (1500.0, "1500"), (123456.7, "123457"),
    (-0.25, "-0.25"), (2e-6, "2e-06"),
])
def test_values_have_four_significant_digits_and_no_powers_of_ten_above_a_ten_thousandth(
        value, text) -> None:
    assert row(la_state(position=value))[JOINT] == f"{text} m"
