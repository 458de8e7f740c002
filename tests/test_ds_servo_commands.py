"""DS servo JSON commands: the schema (what is accepted, what is refused), the driver (which
frames each op becomes) and ``busgate encode`` / ``busgate decode`` on the manual's frames."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from busgate.codecs import ds_servo as ds
from busgate.gateway.cli import main
from busgate.gateway.drivers.ds_servo import frames_for
from busgate.schemas import ds_servo as schema


def parse(command: dict):
    return schema.COMMAND_ADAPTER.validate_json(json.dumps(command))


# --- schema ----------------------------------------------------------------------------------

VALID = [
    ({"op": "ping"}, schema.Ping),
    ({"op": "read", "address": 0x38, "length": 2}, schema.Read),
    ({"op": "read", "address": 0x00, "length": 0x43}, schema.Read),
    ({"op": "write", "address": 0x2A, "data": "07D003e8"}, schema.Write),
    ({"op": "write", "address": 0x30, "data": "01"}, schema.Write),
    ({"op": "move", "position": 4095}, schema.Move),
    ({"op": "move", "position": 0, "time_ms": 65535, "deferred": True}, schema.Move),
    ({"op": "action"}, schema.Action),
    ({"op": "group_move", "targets": [{"id": 1, "position": 2000, "time_ms": 1000}]},
     schema.GroupMove),
    ({"op": "torque", "on": False}, schema.Torque),
    ({"op": "set_id", "new_id": 250}, schema.SetId),
    ({"op": "goto_preset", "n": 3}, schema.GotoPreset),
    ({"op": "store_preset", "n": 1}, schema.StorePreset),
    ({"op": "reset", "client": "bench-1"}, schema.Reset),
]


@pytest.mark.parametrize(("command", "model"), VALID)
def test_each_op_parses(command, model):
    assert type(parse(command)) is model


def test_move_defaults():
    move = parse({"op": "move", "position": 10})
    assert (move.time_ms, move.deferred) == (0, False)


def test_group_move_takes_fifty_distinct_targets():
    targets = [{"id": i, "position": 1, "time_ms": 2} for i in range(1, 51)]
    assert len(parse({"op": "group_move", "targets": targets}).targets) == 50


REFUSED = [
    {"op": "ping", "extra": 1},
    {"op": "estop"},
    {"position": 100},
    {"op": "read", "address": 0x42, "length": 2},  # past the table
    {"op": "read", "address": 0x43, "length": 1},
    {"op": "read", "address": 0x38, "length": 0},
    {"op": "read", "address": "56", "length": 2},
    {"op": "write", "address": 0x38, "data": "07ff"},  # read only
    {"op": "write", "address": 0x07, "data": "00"},  # not in the table
    {"op": "write", "address": 0x3C, "data": "01"},  # address-only command
    {"op": "write", "address": 0x2A, "data": "1000"},  # position 4096
    {"op": "write", "address": 0x2A, "data": "07d"},  # not whole bytes
    {"op": "write", "address": 0x2A, "data": ""},
    {"op": "write", "address": 0x05, "data": "fe"},  # broadcast id is no servo id
    {"op": "move", "position": 4096},
    {"op": "move", "position": -1},
    {"op": "move", "position": 2000.0},
    {"op": "move", "position": "2000"},
    {"op": "move", "position": 1, "time_ms": 65536},
    {"op": "move", "position": 1, "time_ms": -1},
    {"op": "move", "position": 1, "deferred": 1},
    {"op": "move", "position": 1, "speed": 3},
    {"op": "group_move", "targets": []},
    {"op": "group_move", "targets": [{"id": i, "position": 1} for i in range(1, 52)]},
    {"op": "group_move", "targets": [{"id": 1, "position": 1}, {"id": 1, "position": 2}]},
    {"op": "group_move", "targets": [{"id": 254, "position": 1}]},
    {"op": "group_move", "targets": [{"id": 0, "position": 1}]},
    {"op": "group_move", "targets": [{"id": 2, "position": 4096}]},
    {"op": "group_move", "targets": [{"id": 2, "position": 1, "client": "x"}]},
    {"op": "torque", "on": 1},
    {"op": "torque"},
    {"op": "set_id", "new_id": 0},
    {"op": "set_id", "new_id": 251},
    {"op": "set_id", "new_id": 254},
    {"op": "goto_preset", "n": 0},
    {"op": "goto_preset", "n": 4},
    {"op": "store_preset", "n": 4},
    {"op": "reset", "client": "no spaces"},
]


@pytest.mark.parametrize("command", REFUSED)
def test_bad_commands_are_refused(command):
    with pytest.raises(ValidationError):
        parse(command)


# --- driver ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("command", "device_id", "frames"),
    [
        ({"op": "ping"}, 1, [ds.Ping(1)]),
        ({"op": "read", "address": 0x38, "length": 2}, 1, [ds.Read(1, 0x38, 2)]),
        ({"op": "write", "address": 0x28, "data": "01"}, 4, [ds.Write(4, 0x28, b"\x01")]),
        ({"op": "move", "position": 2048, "time_ms": 1000}, 254,
         [ds.Write(254, 0x2A, bytes.fromhex("080003e8"))]),
        ({"op": "move", "position": 2000, "time_ms": 1000, "deferred": True}, 1,
         [ds.RegWrite(1, 2000, 1000)]),
        ({"op": "action"}, 7, [ds.Action()]),
        ({"op": "group_move", "targets": [{"id": 3, "position": 5}, {"id": 1, "position": 6}]}, 9,
         [ds.SyncWrite((ds.SyncTarget(3, 5, 0), ds.SyncTarget(1, 6, 0)))]),
        ({"op": "torque", "on": True}, 2, [ds.Write(2, 0x28, b"\x01")]),
        ({"op": "torque", "on": False}, 2, [ds.Write(2, 0x28, b"\x00")]),
        ({"op": "set_id", "new_id": 1}, 254, [ds.Write(254, 0x05, b"\x01")]),
        ({"op": "goto_preset", "n": 1}, 5, [ds.Write(5, 0x3C, b"")]),
        ({"op": "goto_preset", "n": 3}, 5, [ds.Write(5, 0x3E, b"")]),
        ({"op": "store_preset", "n": 2}, 5, [ds.Write(5, 0x18, b"")]),
        ({"op": "reset"}, 1, [ds.Reset(1)]),
    ],
)
def test_frames_for(command, device_id, frames):
    assert frames_for(parse(command), device_id) == frames


commands = st.sampled_from([command for command, _ in VALID]).map(parse)


@given(commands, st.integers(1, 250))
def test_every_valid_command_reaches_a_servo_intact(command, device_id):
    for frame in frames_for(command, device_id):
        decoder = ds.CommandDecoder()
        decoder.feed(ds.encode(frame))
        assert list(decoder.events()) == [frame]


# --- CLI -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "lines"),
    [
        # manual 2.1
        (["--id", "254", '{"op":"move","position":2048,"time_ms":1000}'],
         ["fffffe07032a080003e8da"]),
        # manual 2.3.1, 2.3.2 (the default id is 1)
        (['{"op":"ping"}'], ["ffff010201fb"]),
        (['{"op":"read","address":56,"length":2}'], ["ffff0104023802be"]),
        # manual 2.3.3
        (["--id", "254", '{"op":"set_id","new_id":1}'], ["fffffe04030501f4"]),
        # manual 2.3.5: two deferred moves, then ACTION
        (["--id", "3", '{"op":"move","position":1000,"time_ms":2000,"deferred":true}'],
         ["ffff0307042a03e807d005"]),
        (['{"op":"action"}'], ["fffffe0205fa"]),
        # manual 2.3.6, with the corrected checksum BA
        (['{"op":"group_move","targets":[{"id":1,"position":2000,"time_ms":1000},'
          '{"id":3,"position":2000,"time_ms":1000}]}'],
         ["fffffe0e832a040107d003e80307d003e8ba"]),
        # manual 2.3.7
        (['{"op":"reset"}'], ["ffff010206f6"]),
    ],
)
def test_cli_encode(capsys, argv, lines):
    assert main(["encode", "ds_servo", *argv]) == 0
    assert capsys.readouterr().out.splitlines() == lines


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--id", "254", '{"op":"ping"}'], "ping cannot be sent to the broadcast id 254"),
        (["--id", "254", '{"op":"move","position":1,"deferred":true}'], "REG WRITE cannot"),
        (["--id", "251", '{"op":"reset"}'], "device_id 251 is out of range"),
        (['{"op":"move","position":5000}'], "position: must be at most 4095, not 5000"),
        (['{"op":"write","address":56,"data":"0000"}'], "read only"),
        (["{not json"], "invalid command"),
    ],
)
def test_cli_encode_refuses_in_one_line(capsys, argv, message):
    assert main(["encode", "ds_servo", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert message in captured.err
    assert len(captured.err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("wire", "decoded"),
    [
        ("FF FF 01 07 04 2A 07 D0 03 E8 07",
         {"event": "RegWrite", "device_id": 1, "position_raw": 2000, "time_ms": 1000}),
        ("FF F5 01 04 00 07 FF F4",
         {"event": "StatusReply", "device_id": 1, "status": [], "data": "07ff"}),
        ("fff5010225d7",
         {"event": "StatusReply", "device_id": 1, "status": ["VOLTAGE", "TEMPERATURE", "OVERLOAD"],
          "data": ""}),
    ],
)
def test_cli_decode(capsys, wire, decoded):
    assert main(["decode", "ds_servo", *wire.split()]) == 0
    assert [json.loads(line) for line in capsys.readouterr().out.splitlines()] == [decoded]


def test_cli_decode_names_the_checksum_of_the_printed_sync_write(capsys):
    printed = "fffffe0e832a040107d003e80307d003e88b"
    assert main(["decode", "ds_servo", printed]) == 1
    err = capsys.readouterr().err
    assert "checksum should be 0xba, frame has 0x8b" in err
