"""The simulated Inspire LA actuator: its rules with a fake clock, then through the real serial
server on a pty with pyserial as the host and the manual's frames on the wire."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from busgate.codecs import inspire_la as la
from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.codecs.inspire_la import (
    ControlCode,
    ControlCommand,
    Fault,
    FollowCommand,
    GroupFollowCommand,
    GroupMoveCommand,
    MoveCommand,
    ReadCommand,
    ReadReply,
    StatusReply,
    Target,
    WriteCommand,
    register_write,
)
from busgate.codecs.timing import uart_time
from busgate.gateway.bus.clock import now
from busgate.gateway.sim.faults import FaultInjector
from busgate.gateway.sim.inspire_la import AUTO_CLEAR_S, InspireLaDevice
from busgate.gateway.sim.inspire_la_physics import AMBIENT_C, HOLD_CURRENT_MA
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.families import PROTOCOLS

T0 = 1000.0  # the fake clock's start; models never read a clock of their own


def control(device_id: int, code: ControlCode) -> ControlCommand:
    return ControlCommand(device_id, code)


def status(device: InspireLaDevice, t: float) -> StatusReply:
    (reply,) = device.handle(control(device.device_id, ControlCode.STATUS), t)
    return reply


def read_u16(device: InspireLaDevice, index: int, t: float = T0) -> int:
    (reply,) = device.handle(ReadCommand(device.device_id, index, 2), t)
    return int.from_bytes(reply.data, "little", signed=True)


# --- the control table ------------------------------------------------------------------


def test_table_holds_the_manuals_defaults() -> None:
    device = InspireLaDevice(1)
    (reply,) = device.handle(ReadCommand(1, 0, 34), T0)
    table = reply.data
    assert table[0:2] == b"\xaa\x55"
    assert table[2] == 1 and table[12] == 3  # id 1, 921600 baud
    assert int.from_bytes(table[32:34], "little") == 1500
    assert read_u16(device, 98) == 800 and read_u16(device, 100) == 600
    assert device.baudrate == 921600
    assert device.turnaround_s == (
        PROTOCOLS["inspire_la"].timing.reply_min_s,
        PROTOCOLS["inspire_la"].timing.reply_max_s,
    )


def test_manual_read_example_is_answered_from_the_table() -> None:
    # 3.5.1: 55 AA 03 01 01 62 02 69 reads the over-temperature limit (here the default 800).
    decoder = la.CommandDecoder()
    decoder.feed(bytes.fromhex("55 AA 03 01 01 62 02 69"))
    (command,) = decoder.events()
    (reply,) = InspireLaDevice(1).handle(command, T0)
    assert la.encode(reply) == bytes.fromhex("AA 55 04 01 01 62 20 03 8B")


def test_writes_are_checked_and_answered_by_the_status_frame() -> None:
    device = InspireLaDevice(1)
    (reply,) = device.handle(register_write(1, la.OVERCURRENT_LIMIT, 1000), T0)
    assert isinstance(reply, StatusReply) and reply.device_id == 1
    assert read_u16(device, 32) == 1000
    refused = [
        WriteCommand(1, 32, (200).to_bytes(2, "little")),  # below 300 mA
        WriteCommand(1, 3, b"\x00"),  # reserved
        WriteCommand(1, 26, b"\x00\x00"),  # read only
        WriteCommand(1, 98, (620).to_bytes(2, "little")),  # < rewarm 600 + 5 °C
        WriteCommand(1, 33, b"\x09"),  # half a register, leaving 0x09E8 = 2536 mA
        WriteCommand(1, 250, bytes(10)),  # past the table's end
    ]
    for command in refused:
        assert isinstance(device.handle(command, T0)[0], StatusReply), command
    assert read_u16(device, 32) == 1000 and read_u16(device, 98) == 800
    # Both temperature limits in one write are judged together (3.7.5's 70.5 and 60.5 °C).
    device.handle(WriteCommand(1, 98, bytes.fromhex("c1025d02")), T0)
    assert (read_u16(device, 98), read_u16(device, 100)) == (705, 605)


def test_id_change_is_in_force_at_once_and_the_reply_comes_from_the_new_id() -> None:
    device = InspireLaDevice(3)
    (reply,) = device.handle(WriteCommand(3, 2, b"\x02"), T0)  # manual 3.7.1
    assert reply.device_id == 2 and device.device_id == 2
    assert device.accepts(MoveCommand(2, 100)) and not device.accepts(MoveCommand(3, 100))


def test_save_and_reboot_keep_only_what_was_saved() -> None:
    device = InspireLaDevice(1)
    device.handle(register_write(1, la.OVERCURRENT_LIMIT, 900), T0)
    device.handle(WriteCommand(1, 2, b"\x05"), T0)
    device.reboot(T0 + 1)
    assert device.device_id == 1 and read_u16(device, 32) == 1500, "unsaved: lost"
    device.handle(register_write(1, la.OVERCURRENT_LIMIT, 900), T0 + 2)
    device.handle(WriteCommand(1, 2, b"\x05"), T0 + 2)
    device.handle(control(5, ControlCode.SAVE), T0 + 2)
    device.handle(register_write(5, la.OVERCURRENT_LIMIT, 700), T0 + 2)  # after the save
    device.reboot(T0 + 3)
    assert device.device_id == 5 and read_u16(device, 32) == 900


def test_baud_code_takes_effect_only_after_save_and_power_cycle() -> None:
    device = InspireLaDevice(1)
    device.handle(register_write(1, la.BAUD_CODE, la.baud_code(115200)), T0)
    assert device.baudrate == 921600
    device.reboot(T0 + 1)
    assert device.baudrate == 921600, "not saved"
    device.handle(register_write(1, la.BAUD_CODE, la.baud_code(115200)), T0 + 2)
    device.handle(control(1, ControlCode.SAVE), T0 + 2)
    assert device.baudrate == 921600, "saved, not yet power-cycled"
    device.reboot(T0 + 3)
    assert device.baudrate == 115200


def test_reboot_stops_motion_where_the_rod_is() -> None:
    device = InspireLaDevice(1)
    device.handle(MoveCommand(1, 2000), T0)
    device.reboot(T0 + 0.25)
    later = status(device, T0 + 2)
    assert later.position_raw == 500 and later.target_raw == 500


# --- motion ------------------------------------------------------------------------------


def test_moves_at_full_stroke_per_stroke_s() -> None:
    device = InspireLaDevice(1)
    (reply,) = device.handle(MoveCommand(1, 2000), T0)
    assert reply.target_raw == 2000 and reply.position_raw == 0
    assert device.position(T0 + 0.5) == pytest.approx(1000)
    assert device.position(T0 + 1.5) == 2000
    device.handle(MoveCommand(1, 1500), T0 + 2)
    assert device.position(T0 + 2.125) == pytest.approx(1750)
    slow = InspireLaDevice(1, stroke_s=4.0)
    slow.handle(MoveCommand(1, 2000), T0)
    assert slow.position(T0 + 1) == pytest.approx(500)
    assert read_u16(slow, 26, T0 + 1) == 500, "current position register"
    with pytest.raises(ValueError, match="stroke_s"):
        InspireLaDevice(1, stroke_s=0)


def test_motion_instructions_reply_or_not_as_the_manual_says() -> None:
    device = InspireLaDevice(3)
    assert len(device.handle(MoveCommand(3, 1000), T0)) == 1  # 0x21
    assert device.handle(MoveCommand(3, 500, reply=False), T0 + 1) == []  # 0x03
    assert device.position(T0 + 1.125) == pytest.approx(750)
    assert len(device.handle(FollowCommand(3, 600), T0 + 2)) == 1  # 0x20
    assert device.handle(FollowCommand(3, 700, reply=False), T0 + 2.01) == []  # 0x19
    assert device.position(T0 + 3) == 700
    # 3.5.2: a write of the target register moves the actuator too.
    device.handle(register_write(3, la.TARGET_POSITION, 1300), T0 + 4)
    assert device.position(T0 + 5) == 1300


def test_out_of_range_target_is_ignored() -> None:
    device = InspireLaDevice(1)
    (reply,) = device.handle(MoveCommand(1, 2500), T0)
    assert reply.target_raw == 0 and device.position(T0 + 2) == 0


def test_broadcast_is_executed_by_all_and_answered_by_none() -> None:
    devices = [InspireLaDevice(i) for i in (1, 2, 3)]
    group = GroupMoveCommand((Target(1, 400), Target(2, 800)))
    assert [d.accepts(group) for d in devices] == [True, True, False]
    assert [d.handle(group, T0) for d in devices[:2]] == [[], []]
    follow = GroupFollowCommand((Target(3, 200),))
    assert devices[2].handle(follow, T0) == []
    for command in (
        MoveCommand(255, 1000),
        control(255, ControlCode.STATUS),
        ReadCommand(255, 2, 1),
        register_write(255, la.OVERCURRENT_LIMIT, 800),
    ):
        assert all(d.accepts(command) for d in devices)
        assert [d.handle(command, T0 + 2) for d in devices] == [[], [], []], command
    assert [d.position(T0 + 2) for d in devices] == [400, 800, 200]
    assert [d.position(T0 + 4) for d in devices] == [1000, 1000, 1000]
    assert all(read_u16(d, 32) == 800 for d in devices)


# --- single control codes ---------------------------------------------------------------


def test_estop_needs_enable_then_a_new_target() -> None:
    device = InspireLaDevice(1)
    device.handle(MoveCommand(1, 2000), T0)
    (reply,) = device.handle(control(1, ControlCode.ESTOP), T0 + 0.25)
    assert reply.position_raw == 500 and reply.current_ma == 0
    device.handle(MoveCommand(1, 1500), T0 + 1)
    assert device.position(T0 + 2) == 500, "e-stopped: targets do not move it"
    device.handle(control(1, ControlCode.ENABLE), T0 + 2)
    assert device.position(T0 + 3) == 500, "enable alone does not move it"
    device.handle(MoveCommand(1, 1500), T0 + 3)
    assert device.position(T0 + 4) == 1500


def test_pause_stops_and_a_new_target_moves_again() -> None:
    device = InspireLaDevice(1)
    device.handle(MoveCommand(1, 2000), T0)
    (reply,) = device.handle(control(1, ControlCode.PAUSE), T0 + 0.5)
    assert reply.position_raw == 1000 and reply.current_ma == 0
    assert device.position(T0 + 2) == 1000
    device.handle(MoveCommand(1, 0), T0 + 2)
    assert device.position(T0 + 3) == 0


# --- status: temperature, current, force -------------------------------------------------


def test_current_is_higher_while_moving_and_heat_follows_it() -> None:
    device = InspireLaDevice(1, stroke_s=1000.0)
    idle = status(device, T0)
    assert idle.current_ma == HOLD_CURRENT_MA and idle.temperature_c == round(AMBIENT_C)
    device.handle(MoveCommand(1, 2000), T0)
    moving = status(device, T0 + 10)
    assert moving.current_ma > 10 * HOLD_CURRENT_MA
    after_a_minute = device.temperature_c(T0 + 60)
    assert AMBIENT_C + 0.1 < after_a_minute < AMBIENT_C + 10, "slowly"
    assert device.temperature_c(T0 + 600) > after_a_minute
    rested = device.temperature_c(T0 + 1000)
    assert device.temperature_c(T0 + 2000) < rested, "cools once the move is over"


def test_force_comes_from_the_force_register_and_can_be_zeroed() -> None:
    device = InspireLaDevice(1)
    device.load_g = 500
    assert status(device, T0).force_g == 500 == read_u16(device, 76)
    device.handle(WriteCommand(1, 31, b"\x01"), T0)  # take the present reading as zero
    assert status(device, T0).force_g == 0 == read_u16(device, 76)
    device.load_g = 0
    assert status(device, T0).force_g == -500
    assert device.handle(ReadCommand(1, 31, 1), T0)[0].data == b"\x00"


# --- faults ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, flag", [("over_current", Fault.OVER_CURRENT), ("stall", Fault.STALL)]
)
def test_over_current_and_stall_clear_twice_by_themselves_then_latch(name, flag) -> None:
    device = InspireLaDevice(1)
    t = T0
    for _ in range(2):
        device.handle(MoveCommand(1, 2000), t)
        device.inject_fault(name, t + 0.1)
        assert status(device, t + 0.1 + AUTO_CLEAR_S - 0.01).faults == flag
        assert device.position(t + 3) == device.position(t + 0.1), "stopped"
        assert status(device, t + 0.1 + AUTO_CLEAR_S).faults == Fault(0)
        t += 10
    device.inject_fault(name, t)
    assert status(device, t + 60).faults == flag, "third time latches"
    device.handle(MoveCommand(1, 0), t + 60)
    assert device.position(t + 62) == device.position(t), "no motion while latched"
    device.handle(control(1, ControlCode.CLEAR_FAULT), t + 61)
    assert status(device, t + 61).faults == Fault(0)
    device.inject_fault(name, t + 70)
    assert status(device, t + 70 + AUTO_CLEAR_S).faults == Fault(0), "count reset by clear"


def test_over_current_trips_when_a_move_draws_more_than_the_limit() -> None:
    device = InspireLaDevice(1, load_g=2000)
    device.handle(register_write(1, la.OVERCURRENT_LIMIT, 300), T0)
    (reply,) = device.handle(MoveCommand(1, 2000), T0)
    assert reply.faults == Fault.OVER_CURRENT and device.position(T0 + 1) == 0


def test_over_temperature_cannot_be_cleared_and_recovers_below_rewarm() -> None:
    device = InspireLaDevice(1)
    device.handle(MoveCommand(1, 2000), T0)
    device.inject_fault("over_temperature", T0 + 0.5)
    hot = status(device, T0 + 0.5)
    assert hot.faults == Fault.OVER_TEMPERATURE and hot.temperature_c > 80
    device.handle(control(1, ControlCode.CLEAR_FAULT), T0 + 1)
    assert status(device, T0 + 1).faults == Fault.OVER_TEMPERATURE
    t = T0 + 1
    while device.temperature_c(t) >= 60:
        assert status(device, t).faults == Fault.OVER_TEMPERATURE
        t += 1
    assert status(device, t).faults == Fault(0)
    device.handle(MoveCommand(1, 0), t)
    assert device.position(t + 1) == 0


def test_lowering_the_over_temperature_limit_below_the_motor_trips_it() -> None:
    device = InspireLaDevice(1)
    device.handle(
        WriteCommand(1, 98, (250).to_bytes(2, "little") + (200).to_bytes(2, "little")), T0
    )
    device.inject_fault("over_temperature", T0)
    assert status(device, T0).faults == Fault.OVER_TEMPERATURE


def test_motor_fault_clears_by_command_or_once_current_flows() -> None:
    device = InspireLaDevice(1)
    device.inject_fault("motor_fault", T0)
    assert status(device, T0 + 1).faults == Fault.MOTOR_FAULT, "at rest < 30 mA"
    device.handle(control(1, ControlCode.CLEAR_FAULT), T0 + 1)
    assert status(device, T0 + 1).faults == Fault(0)
    device.inject_fault("motor_fault", T0 + 2)
    device.handle(MoveCommand(1, 2000), T0 + 2)
    assert status(device, T0 + 2.1).faults == Fault(0)


def test_unknown_fault_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="motor_fault, over_current, over_temperature, stall"):
        InspireLaDevice(1).inject_fault("encoder", T0)


def test_reboot_forgets_faults_but_not_heat() -> None:
    device = InspireLaDevice(1)
    for t in (T0, T0 + 10, T0 + 20):
        device.inject_fault("stall", t)
    device.inject_fault("over_temperature", T0 + 21)
    device.reboot(T0 + 22)
    assert status(device, T0 + 22).faults == Fault.OVER_TEMPERATURE, "still hot"


def test_registry_makes_the_model_with_cli_options() -> None:
    devices = make_devices("inspire_la", [1, 2], stroke_s=2.0)
    assert [d.device_id for d in devices] == [1, 2]
    assert devices[0].speed_per_s == 1000
    with pytest.raises(TypeError):
        make_devices("inspire_la", [1], heartbeat_ms=10)


# --- through the serial server, with pyserial as the host -----------------------------------


def wire_status(device_id: int) -> bytes:
    return la.encode(control(device_id, ControlCode.STATUS))


def decode_replies(data: bytes) -> list[object]:
    decoder = la.ReplyDecoder()
    decoder.feed(data)
    return list(decoder.events())


@pytest.fixture
def sim():
    devices = [InspireLaDevice(1), InspireLaDevice(3)]
    simulator = SerialSimulator(la, devices, baudrate=921600, faults=FaultInjector(seed=1))
    with simulator, serial.Serial(simulator.port, 921600, timeout=10) as host:
        yield simulator, host


def test_manual_frames_get_the_manuals_replies(sim) -> None:
    _, host = sim
    host.write(bytes.fromhex("55 AA 04 03 21 37 E8 03 4A"))  # 3.7.2 move id 3 to 1000
    (reply,) = decode_replies(host.read(22))
    assert isinstance(reply, StatusReply) and reply.device_id == 3 and reply.target_raw == 1000
    host.write(bytes.fromhex("55 AA 03 01 01 62 02 69"))  # 3.5.1 read
    assert decode_replies(host.read(9)) == [ReadReply(1, 0x62, (800).to_bytes(2, "little"))]
    host.write(bytes.fromhex("55 AA 03 03 02 02 02 0C"))  # 3.7.1 id 3 → 2
    (reply,) = decode_replies(host.read(22))
    assert reply.device_id == 2
    host.write(wire_status(2))
    assert decode_replies(host.read(22))[0].device_id == 2


def test_no_reply_frames_and_broadcast_are_silent(sim, before_proof) -> None:
    simulator, host = sim
    host.write(bytes.fromhex("55 AA 04 03 19 37 E8 03 42"))  # follow, no reply (erratum)
    host.write(la.encode(GroupMoveCommand((Target(1, 2000), Target(3, 0)))))
    host.write(la.encode(control(255, ControlCode.STATUS)))
    proof = []

    def prove() -> None:
        host.write(wire_status(1))
        proof.extend(decode_replies(host.read(22)))

    assert before_proof(simulator, 0, 3, prove) == [], "a frame without a reply was answered"
    assert proof[0].target_raw == 2000
    received = [r.frame for r in simulator.recorder.received()]
    assert received == ["FollowCommand", "GroupMoveCommand", "ControlCommand", "ControlCommand"]


def test_reply_never_beats_wire_time_plus_turnaround() -> None:
    baud = 115200
    with (
        SerialSimulator(la, [InspireLaDevice(1)], baudrate=baud) as simulator,
        serial.Serial(simulator.port, baud, timeout=10) as host,
    ):
        request = wire_status(1)
        floor = uart_time(len(request) + la.STATUS_REPLY_SIZE, baud)
        floor += PROTOCOLS["inspire_la"].timing.reply_min_s
        for _ in range(3):
            started = time.perf_counter()
            host.write(request)
            reply = host.read(la.STATUS_REPLY_SIZE)
            elapsed = time.perf_counter() - started
            assert len(reply) == la.STATUS_REPLY_SIZE
            assert elapsed >= floor  # 30 bytes at 115200 = 2.6 ms, + 120 µs
        (rx, *_) = simulator.recorder.received()
        assert rx.wire == request.hex() and rx.frame == "ControlCommand" and rx.device_id == 1
        assert rx.end - rx.start == pytest.approx(uart_time(len(request), baud))
        tx = next(r for r in simulator.recorder.records if r.direction == "tx")
        assert tx.start - rx.end >= PROTOCOLS["inspire_la"].timing.reply_min_s


def test_server_faults_as_the_host_sees_them(sim, wait_for, before_proof, next_reply) -> None:
    simulator, host = sim
    faults = simulator.faults

    faults.configure(drop_rate=1.0, silent_ids=frozenset({3}))
    mark = len(simulator.recorder.records)
    host.write(wire_status(1))  # its reply dropped
    host.write(wire_status(3))  # a silent id: no reply made
    # The simulator takes frames in order: once it has the second, the first was dealt with.
    wait_for(lambda: len(simulator.recorder.received()) >= 2)
    faults.configure(drop_rate=0.0)

    def prove() -> None:
        host.write(wire_status(1))
        assert isinstance(decode_replies(host.read(22))[0], StatusReply)

    assert before_proof(simulator, mark, 2, prove) == [], "a dropped or silent reply went out"

    faults.configure(silent_ids=frozenset(), bad_checksum_rate=1.0)
    host.write(wire_status(1))
    assert isinstance(decode_replies(host.read(22))[0], ChecksumMismatch)

    faults.configure(bad_checksum_rate=0.0, garbage_rate=1.0)
    mark = len(simulator.recorder.records)
    host.write(wire_status(1))
    events = decode_replies(host.read(len(next_reply(simulator, mark).wire) // 2))
    assert isinstance(events[0], Discarded) and isinstance(events[-1], StatusReply)

    faults.configure(garbage_rate=0.0, late_rate=1.0, late_s=0.08)
    started = time.perf_counter()
    host.write(wire_status(1))
    assert len(host.read(22)) == 22
    assert time.perf_counter() - started >= 0.08


def test_bad_frames_do_not_stop_the_server(sim) -> None:
    simulator, host = sim
    out_of_range = bytes.fromhex("55 AA 04 01 21 37 C4 09")  # target 2500
    host.write(out_of_range + bytes([sum(out_of_range[2:]) & 0xFF]) + b"\x00\x13")
    (reply,) = decode_replies(host.read(22))
    assert reply.target_raw == 0, "ignored, answered"
    host.write(wire_status(1))
    assert len(host.read(22)) == 22
    assert [r.frame for r in simulator.recorder.received()][:2] == ["MoveCommand", "Discarded"]


def test_reboot_through_the_server(sim) -> None:
    simulator, host = sim
    host.write(la.encode(WriteCommand(1, 2, b"\x07")))
    assert decode_replies(host.read(22))[0].device_id == 7
    simulator.devices[0].reboot(now())
    host.write(wire_status(1))
    assert decode_replies(host.read(22))[0].device_id == 1, "unsaved id forgotten"


def test_unplug_and_replug_behind_a_link(tmp_path: Path) -> None:
    by_id = tmp_path / "usb-inspire-la"
    device = InspireLaDevice(1)
    with SerialSimulator(la, [device], baudrate=921600, link=PtyLink(str(by_id))) as simulator:
        with serial.Serial(str(by_id), 921600, timeout=10) as host:
            host.write(la.encode(MoveCommand(1, 1200)))
            assert len(host.read(22)) == 22
            simulator.unplug()
            deadline = time.monotonic() + 10
            while by_id.exists() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert not by_id.exists()
            with pytest.raises(serial.SerialException):
                host.read(1)
        simulator.replug()
        deadline = time.monotonic() + 10
        while not by_id.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        with serial.Serial(str(by_id), 921600, timeout=10) as host:
            host.write(wire_status(1))
            (reply,) = decode_replies(host.read(22))
            assert reply.target_raw == 1200, "the actuator kept its state over the unplug"


def test_busgate_sim_cli_serves_until_sigterm() -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "busgate.gateway.cli", "sim", "inspire_la", "--ids", "1,3",
         "--baudrate", "115200", "--stroke-s", "2"],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    try:
        first = process.stdout.readline()
        assert first.startswith("PORT ")
        with serial.Serial(first.split(maxsplit=1)[1].strip(), 115200, timeout=10) as host:
            host.write(bytes.fromhex("55 AA 04 03 21 37 E8 03 4A"))
            (reply,) = decode_replies(host.read(22))
            assert reply.device_id == 3 and reply.target_raw == 1000
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=5) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
