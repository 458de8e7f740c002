"""``busgate decode`` names the registers a reply carries: by the register table's name, with
the raw value and the value in the table's unit, under ``"registers"``; every key printed
before stays as it was. The frames are the manuals' examples wherever one exists."""

from __future__ import annotations

import json

from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as can
from busgate.codecs import zlac706_rs232 as rs232
from busgate.codecs.can_frame import CanFrame
from busgate.gateway.cli import main
from busgate.gateway.cli.jsonify import to_jsonable
from tests.gateway_process import run_busgate


def _decode(capsys, protocol: str, *wire: str) -> list[dict]:
    assert main(["decode", protocol, *wire]) == 0
    return [json.loads(line) for line in capsys.readouterr().out.splitlines()]


def _entry(register: str, address: int, raw: int, value, unit: str | None) -> dict:
    return {"register": register, "address": address, "raw": raw, "value": value, "unit": unit}


# --- Inspire LA read replies ----------------------------------------------------------------


def test_the_manuals_read_reply_is_the_over_temperature_limit_in_degrees():
    """3.5.1: a read of index 0x62 answered 58 02 = 600 tenths of a degree, through the real
    ``busgate`` process."""
    result = run_busgate("decode", "inspire_la", "aa55040101625802c2")
    assert (result.returncode, result.stderr) == (0, "")
    assert json.loads(result.stdout) == {
        "event": "ReadReply", "device_id": 1, "index": 98, "data": "5802",
        "registers": [_entry("overtemp_limit", 98, 600, 60.0, "°C")],
    }  # fmt: skip


def test_a_read_of_several_registers_names_each_in_address_order(capsys):
    """Both limits in one read, with the values of the manual's write example 3.7.5."""
    wire = "aa5506010162c1025d028c"
    assert la.encode(la.ReadReply(1, 98, bytes.fromhex("c1025d02"))).hex() == wire
    (line,) = _decode(capsys, "inspire_la", wire)
    assert line == {
        "event": "ReadReply", "device_id": 1, "index": 98, "data": "c1025d02",
        "registers": [
            _entry("overtemp_limit", 98, 705, 70.5, "°C"),
            _entry("rewarm_temperature", 100, 605, 60.5, "°C"),
        ],
    }  # fmt: skip


def test_only_whole_registers_are_named(capsys):
    """A read from reserved 97 on: the byte at 97 and the first half of 100–101 are in no
    whole register, so only 98–99 is named; ``data`` keeps all four bytes."""
    wire = la.encode(la.ReadReply(1, 97, bytes.fromhex("00580258"))).hex()
    (line,) = _decode(capsys, "inspire_la", wire)
    assert line["data"] == "00580258"
    assert line["registers"] == [_entry("overtemp_limit", 98, 600, 60.0, "°C")]


def test_tenths_of_a_degree_carry_no_binary_noise(capsys):
    """202 × 0.1 is 20.200000000000003 as a float; the value prints as 20.2."""
    wire = la.encode(la.ReadReply(1, 100, (202).to_bytes(2, "little"))).hex()
    (line,) = _decode(capsys, "inspire_la", wire)
    assert line["registers"] == [_entry("rewarm_temperature", 100, 202, 20.2, "°C")]


def test_positions_read_in_stroke_units(capsys):
    wire = la.encode(la.ReadReply(3, 26, (-20).to_bytes(2, "little", signed=True))).hex()
    (line,) = _decode(capsys, "inspire_la", wire)
    assert line["registers"] == [_entry("current_position", 26, -20, -20, "stroke units")]


def test_unknown_registers_and_half_registers_stay_raw(capsys):
    """Reserved addresses 16–17, and one byte of the two-byte limit: the line is exactly what
    it was before registers were named."""
    reserved = la.encode(la.ReadReply(1, 0x10, bytes.fromhex("0102"))).hex()
    half = la.encode(la.ReadReply(1, 98, bytes.fromhex("58"))).hex()
    assert _decode(capsys, "inspire_la", reserved, half) == [
        {"event": "ReadReply", "device_id": 1, "index": 16, "data": "0102"},
        {"event": "ReadReply", "device_id": 1, "index": 98, "data": "58"},
    ]


def test_replies_without_register_values_are_unchanged(capsys):
    """The 3.4.1 write reply (one reserved byte) names nothing."""
    assert _decode(capsys, "inspire_la", "aa5503010237003d") == [
        {"event": "WriteReply", "device_id": 1, "index": 55, "reserved": 0},
    ]


# --- ZLAC706 CAN: write echoes (there is no read) -------------------------------------------


def test_can_write_echoes_are_named_by_register(capsys):
    """Echoes of the manual's writes (tables 3–6, node 1), the 0x16 one as the manual prints
    the reply (``00 fb 00 16 00 01 e2 40``)."""
    lines = _decode(
        capsys,
        "zlac706_can",
        "001#00fb00160001e240",
        "001#00fb001100000555",
        "001#00fb001300000a0b",
        "001#00fb0008000009c4",
        "001#00fb00190000003f",
        "001#00fb002d00001f40",
        "001#00fb002000000bb8",
    )
    assert lines[0] == {
        "event": "WriteAck", "device_id": 1, "register": "TARGET_POSITION", "value": 123456,
        "group": 0, "registers": [_entry("target_position", 0x16, 123456, 123456, "pulses")],
    }  # fmt: skip
    assert [line["registers"] for line in lines[1:]] == [
        [_entry("target_speed", 0x11, 0x555, round(0x555 * 3000 / 8192, 9), "rpm")],  # 500 rpm
        [_entry("speed_ramp", 0x13, 0x0A0B, {"accel": 1000, "decel": 1100}, "ms")],
        [_entry("target_torque", 0x08, 2500, 8.0, "A")],  # 2500 ↔ 8 A
        [_entry("work_mode", 0x19, 0x3F, "POSITION", None)],
        [_entry("rated_current", 0x2D, 8000, 8000, "mA")],
        [_entry("position_kp", 0x20, 3000, 3000, None)],
    ]


def test_can_frames_without_a_known_register_stay_raw(capsys):
    """"No such register", an echo of a register outside the table, a heartbeat (its
    register numbers are not the table's) and an alarm report name nothing."""
    assert _decode(
        capsys,
        "zlac706_can",
        "001#00ff00110000000a",
        "001#00fb00990000000a",
        "001#00fe0021001e043f",
        "001#00ff00eb08080808",
    ) == [
        {"event": "NoSuchRegister", "device_id": 1, "register": "TARGET_SPEED", "value": 10,
         "group": 0},
        {"event": "WriteAck", "device_id": 1, "register": 153, "value": 10, "group": 0},
        {"event": "HeartbeatCurrentSpeed", "device_id": 1, "current_raw": 30, "speed_raw": 1087,
         "group": 0, "current_a": 0.3, "speed_rpm": 1087 * 3000 / 8192},
        {"event": "AlarmReport", "device_id": 1, "alarms": ["ENCODER_FAULT"], "group": 0},
    ]  # fmt: skip


def test_a_ramp_echo_that_does_not_fit_its_two_bytes_has_no_value(capsys):
    (line,) = _decode(capsys, "zlac706_can", "001#00fb001201000a0a")
    assert line["value"] == 0x01000A0A
    assert line["registers"] == [_entry("position_ramp", 0x12, 0x01000A0A, None, "ms")]


# --- ZLAC706 RS232 monitor frames, DS replies -----------------------------------------------


def test_rs232_monitor_frames_are_named_by_item(capsys):
    """The manual's monitor reply (8.2.2); an ack carries no value and names nothing."""
    wire = "0909 80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e e80000e8 e9271020"
    lines = _decode(capsys, "zlac706_rs232", wire)
    assert lines[0] == {"event": "Ack", "register": "POSITION_RAMP"}
    assert lines[3] == {
        "event": "OutputCurrent", "current_raw": 17, "current_a": 0.17,
        "registers": [_entry("current", 0xE2, 17, 0.17, "A")],
    }  # fmt: skip
    assert [line["registers"][0]["value"] for line in lines[1:]] == [
        1, 28, 0.17, 270 * 6000 / 16384, 0, 10000, 0, 10000,
    ]  # fmt: skip
    assert [line["registers"][0]["unit"] for line in lines[1:]] == [
        None, "V", "A", "rpm", "pulses", "pulses", "pulses", "pulses",
    ]  # fmt: skip


def test_a_ds_reply_carries_no_address_and_stays_raw(capsys):
    """2.3.2: the present position read answers ``07 ff``; nothing in the reply says from
    which address."""
    assert _decode(capsys, "ds_servo", "fff501040007fff4") == [
        {"event": "StatusReply", "device_id": 1, "status": [], "data": "07ff"},
    ]


# --- never raising ----------------------------------------------------------------------------


@given(st.integers(0, la.TABLE_SIZE - 1), st.binary(max_size=la.MAX_DATA))
def test_any_la_read_reply_names_without_raising(index, data):
    named = la.readings(la.ReadReply(1, index, data))
    json.dumps(to_jsonable(named))
    assert all(index <= r.address and r.address < index + len(data) for r in named)


@given(st.integers(0, 255), st.integers(-(1 << 31), (1 << 31) - 1))
def test_any_can_echo_names_without_raising(register, value):
    decoder = can.ReplyDecoder()
    decoder.feed(CanFrame(1, bytes((0, 0xFB, 0, register)) + value.to_bytes(4, "big", signed=True)))
    (echo,) = decoder.events()
    named = can.readings(echo)
    json.dumps(to_jsonable(named))
    assert len(named) == (can.REGISTERS.at(register) is not None)


@given(st.binary(max_size=64))
def test_any_rs232_reply_names_without_raising(wire):
    decoder = rs232.ReplyDecoder()
    decoder.feed(wire)
    for event in decoder.events():
        json.dumps(to_jsonable(rs232.readings(event)))
