"""ZLAC706 commands end to end: the shared units, the schema, both drivers and the CLI."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from busgate.codecs import zlac706_can as can
from busgate.codecs import zlac706_rs232 as rs232
from busgate.codecs.errors import EncodeError
from busgate.codecs.zlac706_common import (
    AlarmFlags,
    ramp_word,
    speed_raw_rounded,
    speed_raw_truncated,
    torque_raw_from_amps,
)
from busgate.errors import CommandError
from busgate.gateway.cli import main
from busgate.gateway.drivers import zlac706_can as can_driver
from busgate.gateway.drivers import zlac706_rs232 as rs232_driver
from busgate.schemas.zlac706 import COMMAND_ADAPTER


def _command(text: str):
    return COMMAND_ADAPTER.validate_json(text)


def _can_wire(text: str, device_id: int = 1) -> list[str]:
    return [str(can.encode(f)) for f in can_driver.frames_for(_command(text), device_id)]


def _rs232_wire(text: str) -> list[str]:
    return [rs232.encode(f).hex() for f in rs232_driver.frames_for(_command(text), 1)]


# --- shared units ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("rpm", "raw"),
    [(500, 0x555), (1000, 0xAAA), (-1000, -2730), (100, 0x111), (50, 0x88), (-50, -136),
     (-100, -273), (200, 546), (-200, -546), (0, 0), (0.3, 0), (-0.5, -1)],
)
def test_speed_truncates_toward_zero(rpm: float, raw: int) -> None:
    assert speed_raw_truncated(rpm) == raw


@pytest.mark.parametrize(("rpm", "raw"), [(30, 0x52), (60, 0xA4), (120, 0x148), (1, 3),
                                          (1000, 2731), (-1, -3), (0, 0)])
def test_speed_limit_rounds(rpm: float, raw: int) -> None:
    assert speed_raw_rounded(rpm) == raw


@pytest.mark.parametrize(("amps", "raw"), [(8, 2500), (4.8, 1500), (0.64, 200), (1.6, 500),
                                           (3.2, 1000), (0, 0), (24, 7500), (-24, -7500)])
def test_torque_from_current(amps: float, raw: int) -> None:
    assert torque_raw_from_amps(amps) == raw


@pytest.mark.parametrize(
    ("convert", "value"),
    [(speed_raw_truncated, 1000.01), (speed_raw_truncated, float("nan")),
     (speed_raw_truncated, True), (speed_raw_rounded, -1001), (speed_raw_truncated, "1"),
     (torque_raw_from_amps, 24.01), (torque_raw_from_amps, float("inf")),
     (torque_raw_from_amps, False)],
)
def test_unit_conversions_refuse_out_of_range(convert, value) -> None:
    with pytest.raises(EncodeError):
        convert(value)


def test_ramps_are_whole_100_ms_steps() -> None:
    assert ramp_word(1000, 1000) == 0x0A0A
    assert ramp_word(0, 25500) == 0x00FF
    for accel, decel in ((150, 100), (100, 25600), (-100, 0)):
        with pytest.raises(EncodeError):
            ramp_word(accel, decel)


def test_alarm_faults_leave_out_state_bits() -> None:
    alarms = AlarmFlags.RUNNING | AlarmFlags.EXTERNAL_CONTROL | AlarmFlags.OVERLOAD
    assert alarms.faults == AlarmFlags.OVERLOAD
    assert not (AlarmFlags.RUNNING | AlarmFlags.EXTERNAL_CONTROL).faults


# --- schema ----------------------------------------------------------------------------------

VALID = [
    '{"op":"set_mode","mode":"position"}',
    '{"op":"enable"}',
    '{"op":"disable"}',
    '{"op":"set_position_mode","relative":true}',
    '{"op":"move","position":-2147483648}',
    '{"op":"velocity","rpm":-1000}',
    '{"op":"velocity","rpm":12.5}',
    '{"op":"torque","current_a":4.8}',
    '{"op":"set_position_ramp","accel_ms":1000,"decel_ms":0}',
    '{"op":"set_velocity_ramp","accel_ms":2000,"decel_ms":25500}',
    '{"op":"set_max_speed","rpm":60}',
    '{"op":"clear_alarm"}',
    '{"op":"home"}',
    '{"op":"set_rated_current","current_ma":8000}',
    '{"op":"set_gain","gain":"velocity_ki","value":500}',
    '{"op":"write","register":45,"value":8000}',
    '{"op":"monitor","client":"ui-1"}',
]


@pytest.mark.parametrize("text", VALID)
def test_every_op_parses(text: str) -> None:
    command = _command(text)
    assert command.op == json.loads(text)["op"]


@pytest.mark.parametrize(
    "text",
    [
        '{"op":"enable","force":true}',  # extra field
        '{"op":"velocity","rpm":"100"}',  # string for a number
        '{"op":"velocity","rpm":1001}',
        '{"op":"velocity"}',
        '{"op":"torque","current_a":-24.5}',
        '{"op":"move","position":2147483648}',
        '{"op":"move","position":1.5}',
        '{"op":"set_position_ramp","accel_ms":150,"decel_ms":100}',  # not a 100 ms step
        '{"op":"set_velocity_ramp","accel_ms":100,"decel_ms":25600}',
        '{"op":"set_max_speed","rpm":-1}',
        '{"op":"set_mode","mode":"external_pulses"}',
        '{"op":"set_position_mode","relative":1}',
        '{"op":"set_rated_current","current_ma":24001}',
        '{"op":"set_gain","gain":"current_ki","value":1}',
        '{"op":"set_gain","gain":"position_kp","value":-1}',
        '{"op":"write","register":256,"value":0}',
        '{"op":"write","register":16,"value":2147483648}',
        '{"op":"jog"}',
    ],
)
def test_bad_commands_are_refused(text: str) -> None:
    with pytest.raises(ValidationError):
        _command(text)


@pytest.mark.parametrize("text", [
    '{"op":"set_mode","mode":"velocity"}', '{"op":"set_gain","gain":"position_kp","value":7}',
    '{"op":"set_mode","mode":"fast"}', '{"op":"set_mode","mode":1}', '{"op":"set_mode"}',
])  # fmt: skip
def test_an_object_parsed_from_json_validates_as_its_text_does(text: str) -> None:
    """The API parses a payload once and validates the object: an enum named by its value
    there is what it is in the text, and a refusal is the same refusal."""

    def outcome(validate, value):
        try:
            return validate(value)
        except ValidationError as exc:
            return [(e["loc"], e["type"]) for e in exc.errors()]

    parsed = outcome(COMMAND_ADAPTER.validate_python, json.loads(text))
    assert parsed == outcome(COMMAND_ADAPTER.validate_json, text)


# --- drivers ---------------------------------------------------------------------------------

BOTH = [
    # op, CAN frames (node 1), RS232 frames: every one a frame printed in the manual.
    ('{"op":"set_mode","mode":"position"}', ["001#00fa00190000003f"], ["0200d0d2"]),
    ('{"op":"set_mode","mode":"velocity"}', ["001#00fa00190000002f"], ["0200c4c6"]),
    ('{"op":"set_mode","mode":"torque"}', ["001#00fa00190000008f"], ["0200c1c3"]),
    ('{"op":"enable"}', ["001#00fa00100000001f"], ["00000101"]),
    ('{"op":"disable"}', ["001#00fa00100000000f"], ["00000000"]),
    ('{"op":"set_position_mode","relative":true}', ["001#00fa00170000005f"], ["51000152"]),
    ('{"op":"set_position_mode","relative":false}', ["001#00fa00170000004f"], ["51000051"]),
    ('{"op":"move","position":10000}', ["001#00fa001600002710"], ["50000050", "0527103c"]),
    ('{"op":"move","position":-10000}', ["001#00fa0016ffffd8f0"], ["50ffff4e", "05d8f0cd"]),
    ('{"op":"move","position":123456}', ["001#00fa00160001e240"], ["50000151", "05e24027"]),
    ('{"op":"velocity","rpm":500}', ["001#00fa001100000555"], ["06055560"]),
    ('{"op":"velocity","rpm":-50}', ["001#00fa0011ffffff78"], ["06ff787d"]),
    ('{"op":"velocity","rpm":200}', ["001#00fa001100000222"], ["0602222a"]),
    ('{"op":"torque","current_a":4.8}', ["001#00fa0008000005dc"], ["0805dce9"]),
    ('{"op":"torque","current_a":8}', ["001#00fa0008000009c4"], ["0809c4d5"]),
    ('{"op":"set_position_ramp","accel_ms":1000,"decel_ms":1000}', ["001#00fa001200000a0a"],
     ["090a0a1d"]),
    ('{"op":"set_position_ramp","accel_ms":5000,"decel_ms":5000}', ["001#00fa001200003232"],
     ["0932326d"]),
    ('{"op":"set_velocity_ramp","accel_ms":1000,"decel_ms":1100}', ["001#00fa001300000a0b"],
     ["0a0a0b1f"]),
    ('{"op":"set_velocity_ramp","accel_ms":2000,"decel_ms":2000}', ["001#00fa001300001414"],
     ["0a141432"]),
    # CAN truncates (1000 rpm → 0x0AAA in table 3), RS232 rounds (note 8: 60 rpm → 0xA4).
    ('{"op":"set_max_speed","rpm":1000}', ["001#00fa001400000aaa"], ["1d0aabd2"]),
    ('{"op":"set_max_speed","rpm":100}', ["001#00fa001400000111"], ["1d01112f"]),
    ('{"op":"set_max_speed","rpm":60}', ["001#00fa0014000000a3"], ["1d00a4c1"]),
    ('{"op":"clear_alarm"}', ["001#00fa00150000007f"], ["4a00004a"]),
    ('{"op":"home"}', ["001#00fa00180000006f"], ["53000053"]),
    ('{"op":"set_rated_current","current_ma":8000}', ["001#00fa002d00001f40"], ["2d1f408c"]),
    ('{"op":"set_rated_current","current_ma":10000}', ["001#00fa002d00002710"], ["2d271064"]),
    ('{"op":"set_gain","gain":"position_kp","value":3000}', ["001#00fa002000000bb8"],
     ["1a0bb8dd"]),
    ('{"op":"set_gain","gain":"velocity_kd","value":0}', ["001#00fa002500000000"], ["42000042"]),
    ('{"op":"write","register":45,"value":8000}', ["001#00fa002d00001f40"], ["2d1f408c"]),
]


@pytest.mark.parametrize(("text", "can_wire", "rs232_wire"), BOTH)
def test_drivers(text: str, can_wire: list[str], rs232_wire: list[str]) -> None:
    assert _can_wire(text) == can_wire
    assert _rs232_wire(text) == rs232_wire


def test_can_node_id_and_broadcast() -> None:
    assert _can_wire('{"op":"enable"}', device_id=10) == ["00a#00fa00100000001f"]
    assert _can_wire('{"op":"enable"}', device_id=0) == ["000#00da00100000001f"]


def test_monitor_is_rs232_only() -> None:
    assert _rs232_wire('{"op":"monitor"}') == ["800080"]
    with pytest.raises(CommandError, match="RS232") as caught:
        can_driver.frames_for(_command('{"op":"monitor"}'), 1)
    assert caught.value.code == "bad_command"


def test_rs232_has_no_current_gains() -> None:
    assert _can_wire('{"op":"set_gain","gain":"current_kd","value":500}') == [
        "001#00fa0027000001f4"
    ]
    with pytest.raises(CommandError, match="current_kd"):
        _rs232_wire('{"op":"set_gain","gain":"current_kd","value":500}')


@pytest.mark.parametrize("register", [0x33, 0x80, 0xE1])
def test_raw_write_refuses_registers_outside_the_table(register: int) -> None:
    text = json.dumps({"op": "write", "register": register, "value": 0})
    with pytest.raises(CommandError):
        _can_wire(text)
    with pytest.raises(CommandError):
        _rs232_wire(text)


def test_values_wider_than_16_bits_fit_can_only() -> None:
    text = '{"op":"set_gain","gain":"position_kp","value":65536}'
    assert _can_wire(text) == ["001#00fa002000010000"]
    with pytest.raises(EncodeError):
        _rs232_wire(text)
    with pytest.raises(EncodeError):
        _rs232_wire('{"op":"write","register":6,"value":-40000}')


def test_raw_write_is_range_checked_per_register() -> None:
    with pytest.raises(EncodeError):
        _can_wire('{"op":"write","register":25,"value":1}')  # work mode takes 2F/3F/8F only


def test_moves_of_extreme_positions_split_and_join() -> None:
    for position in (-(1 << 31), (1 << 31) - 1, -1, 65536):
        command = _command(json.dumps({"op": "move", "position": position}))
        frames = rs232_driver.frames_for(command, 1)
        assert rs232.join_position(frames[0].value, frames[1].value) == position


# --- CLI -------------------------------------------------------------------------------------


def test_cli_issue_examples(capsys) -> None:
    assert main(["encode", "zlac706_can", "--id", "1", '{"op":"velocity","rpm":-1000}']) == 0
    assert capsys.readouterr().out == "001#00fa0011fffff556\n"
    assert main(["encode", "zlac706_rs232", '{"op":"move","position":10000}']) == 0
    assert capsys.readouterr().out == "50000050\n0527103c\n"


def test_cli_refuses_id_on_rs232_and_monitor_on_can(capsys) -> None:
    assert main(["encode", "zlac706_rs232", "--id", "1", '{"op":"enable"}']) == 2
    assert "no device id" in capsys.readouterr().err
    assert main(["encode", "zlac706_can", '{"op":"monitor"}']) == 2
    err = capsys.readouterr().err
    assert "RS232" in err and "Traceback" not in err


def test_cli_refuses_out_of_range_rs232_value(capsys) -> None:
    assert main(["encode", "zlac706_rs232", '{"op":"write","register":6,"value":70000}']) == 2
    assert "out of range" in capsys.readouterr().err


def test_cli_decodes_monitor_reply(capsys) -> None:
    wire = "80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e e80000e8 e9271020"
    assert main(["decode", "zlac706_rs232", wire]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    # Each frame also names its item under "registers" (tests/test_decode_registers.py).
    assert all(line.pop("registers") for line in lines)
    assert lines[0] == {"event": "StatusReport", "alarms": ["RUNNING"]}
    assert lines[2] == {"event": "OutputCurrent", "current_raw": 17, "current_a": 0.17}
    assert len(lines) == 8


def test_cli_decode_names_a_bad_checksum(capsys) -> None:
    assert main(["decode", "zlac706_rs232", "--as", "command", "0527103d"]) == 1
    assert "checksum" in capsys.readouterr().err


def test_cli_decodes_can_heartbeat(capsys) -> None:
    assert main(["decode", "zlac706_can", "001#00fe0021001e043f"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert json.loads(line) == {
        "event": "HeartbeatCurrentSpeed", "device_id": 1, "current_raw": 30, "speed_raw": 1087,
        "group": 0, "current_a": 0.3, "speed_rpm": 1087 * 3000 / 8192,
    }
