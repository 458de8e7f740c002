"""Inspire LA above the codec: the control table, the JSON commands, the driver and the CLI."""

from __future__ import annotations

import json
import typing

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from busgate.codecs import inspire_la as la
from busgate.codecs.errors import EncodeError
from busgate.gateway.cli import main
from busgate.gateway.drivers.inspire_la_frames import frames_for
from busgate.schemas import inspire_la as schema

# --- the control table ----------------------------------------------------------------------


def test_control_table_as_the_manual_gives_it():
    rows = {
        r.name: (r.address, r.size, r.access.value, r.minimum, r.maximum, r.default)
        for r in la.REGISTERS
    }
    assert rows == {
        "id": (2, 1, "rw", 1, 254, 1),
        "baud_code": (12, 1, "rw", 0, 3, 3),
        "current_position": (26, 2, "r", -20, 2020, None),
        "force_zero": (31, 1, "rw", 1, 1, 0),
        "overcurrent_limit": (32, 2, "rw", 300, 1500, 1500),
        "target_position": (55, 2, "rw", 0, 2000, None),
        "force": (76, 2, "r", -32767, None, None),
        "force_raw": (78, 2, "r", None, None, None),
        "overtemp_limit": (98, 2, "rw", 250, 800, 800),
        "rewarm_temperature": (100, 2, "rw", 200, 750, 600),
    }
    assert la.REGISTERS.at(90) is None and la.REGISTERS.at(1) is None


def test_temperature_conversion():
    assert la.temperature_raw(70.5) == 705
    assert la.temperature_raw(60) == 600
    with pytest.raises(EncodeError):
        la.temperature_raw(70.55)


def test_temperature_cross_rule():
    la.check_temperature_limits(705, 655)  # exactly 5 °C apart
    with pytest.raises(EncodeError) as info:
        la.check_temperature_limits(705, 656)
    assert info.value.field == "overtemp_limit"


def test_baud_codes():
    assert [la.baud_code(b) for b in (19200, 57600, 115200, 921600)] == [0, 1, 2, 3]
    with pytest.raises(EncodeError):
        la.baud_code(9600)


# --- JSON commands --------------------------------------------------------------------------

VALID = [
    ('{"op":"move","position":1000}', schema.Move),
    ('{"op":"move","position":0,"reply":false}', schema.Move),
    ('{"op":"follow","position":2000,"client":"arm-1"}', schema.Follow),
    ('{"op":"enable"}', schema.Enable),
    ('{"op":"estop"}', schema.Estop),
    ('{"op":"pause"}', schema.Pause),
    ('{"op":"save"}', schema.Save),
    ('{"op":"status"}', schema.Status),
    ('{"op":"clear_fault"}', schema.ClearFault),
    ('{"op":"read","index":98,"length":2}', schema.Read),
    ('{"op":"read","index":2,"length":253}', schema.Read),
    ('{"op":"write","index":55,"data":"1405"}', schema.Write),
    ('{"op":"write","index":98,"data":"C1025D02"}', schema.Write),
    ('{"op":"set_id","new_id":254}', schema.SetId),
    ('{"op":"set_overcurrent","current_ma":300}', schema.SetOvercurrent),
    ('{"op":"set_overtemp","temp_c":70.5}', schema.SetOvertemp),
    ('{"op":"set_overtemp","temp_c":80}', schema.SetOvertemp),
    ('{"op":"set_rewarm","temp_c":20}', schema.SetRewarm),
    ('{"op":"set_baudrate","baudrate":921600}', schema.SetBaudrate),
    ('{"op":"zero_force"}', schema.ZeroForce),
    ('{"op":"group_move","targets":[{"id":1,"position":0}]}', schema.GroupMove),
    ('{"op":"group_follow","targets":[{"id":1,"position":0},{"id":254,"position":2000}]}',
     schema.GroupFollow),
]  # fmt: skip


@pytest.mark.parametrize(("text", "model"), VALID)
def test_valid_commands_parse(text, model):
    assert type(schema.COMMAND_ADAPTER.validate_json(text)) is model


def test_valid_examples_cover_every_op():
    models = typing.get_args(typing.get_args(schema.Command)[0])
    assert {type(schema.COMMAND_ADAPTER.validate_json(text)) for text, _ in VALID} == set(models)


def _targets(n: int) -> str:
    return json.dumps([{"id": i, "position": 0} for i in range(1, n + 1)])


INVALID = [
    '{"op":"move"}',
    '{"op":"move","position":2001}',
    '{"op":"move","position":-1}',
    '{"op":"move","position":"1000"}',
    '{"op":"move","position":1000.0}',
    '{"op":"move","position":true}',
    '{"op":"move","position":1000,"reply":1}',
    '{"op":"move","position":1000,"speed":5}',
    '{"op":"follow","position":3000}',
    '{"op":"enable","position":1}',
    '{"op":"status","client":"bad id!"}',
    '{"op":"jump"}',
    '{"position":1000}',
    '{"op":"read","index":255,"length":1}',
    '{"op":"read","index":0,"length":0}',
    '{"op":"read","index":250,"length":6}',
    '{"op":"write","index":55,"data":"140"}',
    '{"op":"write","index":55,"data":"zz"}',
    '{"op":"write","index":55,"data":""}',
    '{"op":"write","index":3,"data":"00"}',
    '{"op":"write","index":26,"data":"0000"}',
    '{"op":"write","index":55,"data":"d207"}',
    '{"op":"write","index":98,"data":"c102a002"}',
    '{"op":"set_id","new_id":0}',
    '{"op":"set_id","new_id":255}',
    '{"op":"set_overcurrent","current_ma":299}',
    '{"op":"set_overcurrent","current_ma":1501}',
    '{"op":"set_overtemp","temp_c":24.9}',
    '{"op":"set_overtemp","temp_c":80.1}',
    '{"op":"set_overtemp","temp_c":70.55}',
    '{"op":"set_overtemp","temp_c":"70"}',
    '{"op":"set_rewarm","temp_c":19.9}',
    '{"op":"set_rewarm","temp_c":75.1}',
    '{"op":"set_baudrate","baudrate":9600}',
    '{"op":"set_baudrate","baudrate":"115200"}',
    '{"op":"zero_force","value":1}',
    '{"op":"group_move","targets":[]}',
    '{"op":"group_move","targets":' + _targets(16) + "}",
    '{"op":"group_move","targets":[{"id":255,"position":0}]}',
    '{"op":"group_move","targets":[{"id":0,"position":0}]}',
    '{"op":"group_move","targets":[{"id":1,"position":2001}]}',
    '{"op":"group_follow","targets":[{"id":1,"position":0},{"id":1,"position":5}]}',
    '{"op":"group_follow","targets":[{"id":1,"position":0,"time_ms":5}]}',
]


@pytest.mark.parametrize("text", INVALID)
def test_invalid_commands_are_refused(text):
    with pytest.raises(ValidationError):
        schema.COMMAND_ADAPTER.validate_json(text)


def test_ranges_come_from_the_control_table():
    properties = schema.Move.model_json_schema()["properties"]["position"]
    assert (properties["minimum"], properties["maximum"]) == (0, 2000)
    temp = schema.SetOvertemp.model_json_schema()["properties"]["temp_c"]
    assert (temp["minimum"], temp["maximum"]) == (25, 80)


@given(st.integers(0, 260), st.binary(max_size=8))
def test_an_accepted_write_always_encodes(index, data):
    text = json.dumps({"op": "write", "index": index, "data": data.hex()})
    try:
        command = schema.COMMAND_ADAPTER.validate_json(text)
    except ValidationError:
        return
    [frame] = frames_for(command, 1)
    assert la.encode(frame)[5] == index


# --- driver ---------------------------------------------------------------------------------

DRIVEN = [
    # (command, device id, wire) — the manual's examples where it has one.
    ('{"op":"move","position":1000}', 3, "55 AA 04 03 21 37 E8 03 4A"),  # 3.7.2
    ('{"op":"move","position":1000,"reply":false}', 3, "55 AA 04 03 03 37 E8 03 2C"),
    ('{"op":"follow","position":1000}', 3, "55 AA 04 03 20 37 E8 03 49"),
    ('{"op":"follow","position":1000,"reply":false}', 3, "55 AA 04 03 19 37 E8 03 42"),
    ('{"op":"estop"}', 3, "55 AA 03 03 04 00 23 2D"),  # 3.7.3
    ('{"op":"enable"}', 3, "55 AA 03 03 04 00 04 0E"),  # 3.7.4
    ('{"op":"pause"}', 3, "55 AA 03 03 04 00 14 1E"),
    ('{"op":"save"}', 3, "55 AA 03 03 04 00 20 2A"),  # 3.7.7
    ('{"op":"status"}', 1, "55 AA 03 01 04 00 22 2A"),  # 3.7.8
    ('{"op":"clear_fault"}', 1, "55 AA 03 01 04 00 1E 26"),  # 3.7.9
    ('{"op":"read","index":98,"length":2}', 1, "55 AA 03 01 01 62 02 69"),  # 3.5.1
    ('{"op":"write","index":55,"data":"1405"}', 1, "55 AA 04 01 02 37 14 05 57"),  # 3.5.2
    ('{"op":"set_id","new_id":2}', 3, "55 AA 03 03 02 02 02 0C"),  # 3.7.1
    ('{"op":"set_overtemp","temp_c":70.5}', 3, "55 AA 04 03 02 62 C1 02 2E"),  # 3.7.5
    ('{"op":"set_rewarm","temp_c":60.5}', 3, "55 AA 04 03 02 64 5D 02 CC"),  # 3.7.5
    ('{"op":"set_overcurrent","current_ma":1000}', 1, "55 AA 04 01 02 20 E8 03 12"),  # 3.7.6
    ('{"op":"set_baudrate","baudrate":115200}', 3, "55 AA 03 03 02 0C 02 16"),
    ('{"op":"zero_force"}', 3, "55 AA 03 03 02 1F 01 28"),
    # Broadcast ops go to 255 whatever the device id.
    ('{"op":"group_move","targets":[{"id":1,"position":1300},{"id":2,"position":1000}]}', 9,
     "55 AA 07 FF F2 01 14 05 02 E8 03 FF"),
    ('{"op":"group_follow","targets":[{"id":15,"position":2000}]}', 1,
     "55 AA 04 FF F3 0F D0 07 DC"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "device_id", "wire"), DRIVEN)
def test_driver_frames(text, device_id, wire):
    command = schema.COMMAND_ADAPTER.validate_json(text)
    assert [la.encode(f) for f in frames_for(command, device_id)] == [bytes.fromhex(wire)]


def test_driver_covers_every_op():
    models = set(typing.get_args(typing.get_args(schema.Command)[0]))
    assert {type(schema.COMMAND_ADAPTER.validate_json(t)) for t, _, _ in DRIVEN} == models


def test_group_follow_frame_for_fifteen_actuators():
    text = '{"op":"group_follow","targets":' + _targets(15) + "}"
    [frame] = frames_for(schema.COMMAND_ADAPTER.validate_json(text), 1)
    assert len(la.encode(frame)) == 51  # 553 µs at 921600
    assert la.expected_reply(frame) is None


# --- CLI ------------------------------------------------------------------------------------


def test_cli_encode_issue_example(capsys):
    assert main(["encode", "inspire_la", "--id", "3", '{"op":"move","position":1000}']) == 0
    assert capsys.readouterr().out == "55aa04032137e8034a\n"


def test_cli_encode_defaults_to_id_1(capsys):
    assert main(["encode", "inspire_la", '{"op":"status"}']) == 0
    assert capsys.readouterr().out == "55aa03010400222a\n"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--id", "0", '{"op":"status"}'], "device_id 0 is out of range [1, 255]"),
        (["--id", "255", '{"op":"read","index":2,"length":1}'], "device_id 255 is out of range"),
        (['{"op":"move","position":2001}'], "position: must be at most 2000, not 2001"),
        (['{"op":"write","index":3,"data":"00"}'], "address 3 is reserved"),
        (["{not json"], "invalid command"),
        # read as the gateway reads a command: not the last of two, nor NaN
        (['{"op":"move","position":1,"position":2}'],
         "error: invalid command: key 'position' appears twice: a command is never guessed\n"),
        (['{"op":"move","position":NaN}'],
         "error: invalid command: payload is not JSON: NaN is not a number JSON allows\n"),
        (['{"op":"mvoe"}'], "error: unknown op `mvoe` for inspire_la (did you mean `move`?)\n"),
        (['{"position":1500}'], "error: missing `op`: every inspire_la command names its op\n"),
    ],
)
def test_cli_encode_refusals_are_one_line(capsys, argv, message):
    assert main(["encode", "inspire_la", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert message in captured.err and captured.err.count("\n") == 1


def test_cli_decode_status_reply(capsys):
    wire = "AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 05 01 08 07 0A 07 99"
    assert main(["decode", "inspire_la", *wire.split()]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "event": "StatusReply",
        "device_id": 1,
        "target_raw": 1003,
        "position_raw": 990,
        "temperature_c": 20,
        "current_ma": 100,
        "force_g": 500,
        "faults": ["STALL", "OVER_CURRENT"],
        "internal_1": 1800,
        "internal_2": 1802,
        "command": 4,  # the cmd byte it came under: the status query's
    }


def test_cli_decode_command(capsys):
    assert main(["decode", "inspire_la", "55aa04031937e80342"]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "event": "FollowCommand", "device_id": 3, "position_raw": 1000, "reply": False,
    }  # fmt: skip


def test_cli_decode_names_the_checksum_of_the_printed_follow_frame(capsys):
    assert main(["decode", "inspire_la", "--as", "command", "55aa04031937e80328"]) == 1
    assert "checksum should be 0x42, frame has 0x28" in capsys.readouterr().err


@pytest.mark.parametrize("wire", ["", " "])
def test_cli_decode_of_no_bytes_says_so(wire, capsys):
    """It printed nothing and exited 0, as if a frame had been decoded."""
    assert main(["decode", "inspire_la", wire]) == 2
    assert capsys.readouterr().err == (
        "busgate decode: error: no bytes to decode: give the frame in hex\n")
