"""The simulated DS servo: its rules with a fake clock, then through SerialSimulator on a real
pty with pyserial as the host and frames from the manual (docs/protocols.md, DS section)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
import serial

from busgate.codecs import ds_servo as ds
from busgate.codecs.timing import uart_time
from busgate.gateway.sim.ds_servo import (
    AMBIENT_C,
    CURRENT_MA,
    OVER_TEMPERATURE_C,
    TOP_SPEED_STEPS_PER_S,
    DsServoDevice,
)
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.families import PROTOCOLS
from tests.serial_host import exchange

OK = ds.ServoStatus(0)
# Manual examples (2.3.1-2.3.7); SYNC WRITE with the checksum corrected to BA (docs/protocols.md).
PING_1 = "FF FF 01 02 01 FB"
PING_1_REPLY = "FF F5 01 02 00 FC"
READ_POSITION_1 = "FF FF 01 04 02 38 02 BE"
READ_POSITION_1_REPLY = "FF F5 01 04 00 07 FF F4"
BROADCAST_ID_TO_1 = "FF FF FE 04 03 05 01 F4"
REG_WRITE_1 = "FF FF 01 07 04 2A 07 D0 03 E8 07"
REG_WRITE_3 = "FF FF 03 07 04 2A 03 E8 07 D0 05"
ACTION = "FF FF FE 02 05 FA"
SYNC_WRITE_1_3 = "FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 BA"
RESET_1 = "FF FF 01 02 06 F6"


def command(text: str) -> ds.Command:
    """The one command the manual's frame ``text`` decodes to."""
    decoder = ds.CommandDecoder()
    decoder.feed(bytes.fromhex(text))
    [event] = decoder.events()
    return event


def read(servo: DsServoDevice, name: str, now: float) -> int:
    register = ds.REGISTERS[name]
    [reply] = servo.handle(ds.Read(servo.device_id, register.address, register.size), now)
    return ds.values_from(register.address, reply.data)[name]


def write(servo: DsServoDevice, address: int, data: bytes, now: float) -> list:
    return servo.handle(ds.Write(servo.device_id, address, data), now)


def move(servo: DsServoDevice, position: int, time_ms: int, now: float) -> None:
    write(servo, ds.MOVE_ADDRESS, position.to_bytes(2, "big") + time_ms.to_bytes(2, "big"), now)


def status(servo: DsServoDevice, now: float) -> ds.ServoStatus:
    [reply] = servo.handle(ds.Ping(servo.device_id), now)
    return reply.status


# --- replies and the control table -----------------------------------------------------------


def test_manual_ping_and_read_get_the_manuals_replies() -> None:
    servo = DsServoDevice(1, position_raw=0x07FF)
    assert [ds.encode(r) for r in servo.handle(command(PING_1), 0.0)] == [
        bytes.fromhex(PING_1_REPLY)]
    assert [ds.encode(r) for r in servo.handle(command(READ_POSITION_1), 0.0)] == [
        bytes.fromhex(READ_POSITION_1_REPLY)]


def test_control_table_starts_at_the_manuals_defaults() -> None:
    servo = DsServoDevice(4)
    [reply] = servo.handle(ds.Read(4, 0x03, ds.TABLE_END - 0x03), 0.0)
    values = ds.values_from(0x03, reply.data)
    assert {name: values[name] for name in (
        "servo_id", "stall_protection_time", "min_angle", "max_angle", "max_torque",
        "speed_adjust", "unload_condition", "centre_offset", "preset_1", "preset_2", "preset_3",
        "move_time")} == {
        "servo_id": 4, "stall_protection_time": 3, "min_angle": 0, "max_angle": 4095,
        "max_torque": 800, "speed_adjust": 30, "unload_condition": 0, "centre_offset": 0,
        "preset_1": 2048, "preset_2": 2048, "preset_3": 2048, "move_time": 0}
    assert values["torque_enable"] == 1, "torque on at power-up: the manual's examples move"
    assert values["target_position"] == values["present_position"] == 2048
    assert values["temperature"] == AMBIENT_C and values["speed"] == 0
    assert values["current"] == CURRENT_MA["holding"] and values["reg_write_pending"] == 0
    assert values["firmware_version"] == 0x011C


def test_write_to_a_read_only_or_unknown_address_is_ignored_and_answered() -> None:
    servo = DsServoDevice(1)
    assert write(servo, 0x38, b"\x00\x00", 0.0) == [ds.StatusReply(1, OK)]
    assert write(servo, 0x07, b"\x55", 0.0) == [ds.StatusReply(1, OK)]
    assert read(servo, "present_position", 0.0) == 2048
    [reply] = servo.handle(ds.Read(1, 0x07, 1), 0.0)
    assert reply.data == b"\x00"
    # On the wire such a frame never reaches the servo: the codec discards it.
    decoder = ds.CommandDecoder()
    decoder.feed(bytes.fromhex("FF FF 01 05 03 38 00 00 BE"))
    assert [type(e).__name__ for e in decoder.events()] == ["Discarded"]


def test_id_change_takes_effect_with_the_next_frame() -> None:
    servo = DsServoDevice(1)
    assert write(servo, 0x05, b"\x09", 0.0) == [ds.StatusReply(1, OK)], "answered as 1"
    assert servo.device_id == 9
    assert servo.accepts(ds.Ping(9)) and not servo.accepts(ds.Ping(1))
    assert servo.handle(ds.Ping(9), 0.0) == [ds.StatusReply(9, OK)]


def test_broadcast_executes_without_reply() -> None:
    servos = [DsServoDevice(2), DsServoDevice(3)]
    frame = command(BROADCAST_ID_TO_1)
    for servo in servos:
        assert servo.accepts(frame) and servo.handle(frame, 0.0) == []
    assert [s.device_id for s in servos] == [1, 1], "the manual's example: every servo is 1"
    off = ds.Write(ds.BROADCAST_ID, 0x28, b"\x00")
    assert servos[0].handle(off, 0.0) == [] and read(servos[0], "torque_enable", 0.0) == 0


def test_accepts_its_id_broadcast_action_and_its_sync_entry() -> None:
    servo = DsServoDevice(3)
    assert servo.accepts(ds.Ping(3)) and not servo.accepts(ds.Ping(4))
    assert servo.accepts(ds.Action()) and servo.accepts(command(SYNC_WRITE_1_3))
    assert not DsServoDevice(2).accepts(command(SYNC_WRITE_1_3))
    assert servo.spontaneous(100.0) == []


def test_unknown_options_and_faults_are_refused() -> None:
    with pytest.raises(TypeError):
        make_devices("ds_servo", [1], stroke_s=1.0)
    with pytest.raises(ValueError, match="encoder"):
        DsServoDevice(1).inject_fault("encoder", 0.0)
    assert [d.device_id for d in make_devices("ds_servo", [1, 2])] == [1, 2]


# --- timed moves -----------------------------------------------------------------------------


def test_timed_move_runs_to_the_target_in_the_move_time() -> None:
    servo = DsServoDevice(1)
    move(servo, 3048, 1000, 10.0)
    assert read(servo, "present_position", 10.5) == 2548
    assert read(servo, "speed", 10.5) == 1000 and read(servo, "current", 10.5) == 250
    assert read(servo, "present_position", 11.0) == 3048
    assert read(servo, "speed", 11.0) == 0
    assert read(servo, "move_time", 11.0) == 1000


def test_move_time_zero_runs_at_top_speed_and_no_move_runs_faster() -> None:
    servo = DsServoDevice(1, position_raw=0)
    move(servo, 4095, 0, 0.0)
    full_s = 4095 / TOP_SPEED_STEPS_PER_S
    assert read(servo, "present_position", full_s / 2) == 2048
    assert read(servo, "present_position", full_s) == 4095
    move(servo, 0, 10, 5.0)  # asks for 10 ms, gets the top speed
    assert read(servo, "present_position", 5.0 + full_s / 2) == 2048


def test_position_only_write_uses_the_move_time_register() -> None:
    servo = DsServoDevice(1)
    write(servo, 0x2C, (2000).to_bytes(2, "big"), 0.0)
    write(servo, 0x2A, (3048).to_bytes(2, "big"), 1.0)
    assert read(servo, "present_position", 2.0) == 2548


def test_targets_are_clamped_to_the_range_and_the_angle_limits() -> None:
    servo = DsServoDevice(1)
    write(servo, 0x0B, (3000).to_bytes(2, "big"), 0.0)
    move(servo, 4000, 0, 0.0)
    assert read(servo, "target_position", 0.0) == 3000
    assert read(servo, "present_position", 5.0) == 3000
    write(servo, 0x0B, (4095).to_bytes(2, "big"), 5.0)
    move(servo, 0xFFFF, 0, 5.0)  # only in-process: the codec refuses > 4095 on the wire
    assert read(servo, "target_position", 5.0) == 4095


# --- torque switch ---------------------------------------------------------------------------


def test_with_torque_off_the_servo_does_not_move() -> None:
    servo = DsServoDevice(1)
    move(servo, 3048, 1000, 0.0)
    write(servo, 0x28, b"\x00", 0.5)
    assert read(servo, "present_position", 2.0) == 2548, "stopped where it was"
    assert read(servo, "current", 2.0) == 0
    move(servo, 100, 0, 2.0)
    assert read(servo, "target_position", 2.0) == 100, "the target is stored"
    assert read(servo, "present_position", 9.0) == 2548, "but nothing moves"
    write(servo, 0x28, b"\x01", 9.0)
    assert read(servo, "target_position", 9.0) == 2548, "torque on holds, no jump"
    assert read(servo, "present_position", 20.0) == 2548


def test_writing_the_torque_it_already_has_does_not_stop_a_move() -> None:
    servo = DsServoDevice(1)
    move(servo, 3048, 1000, 0.0)
    write(servo, 0x28, b"\x01", 0.5)
    assert read(servo, "present_position", 1.0) == 3048


# --- REG WRITE + ACTION, SYNC WRITE ----------------------------------------------------------


def test_manual_reg_write_then_action_starts_both_servos_at_once() -> None:
    one, three, two = DsServoDevice(1), DsServoDevice(3), DsServoDevice(2)
    assert one.handle(command(REG_WRITE_1), 0.0) == [ds.StatusReply(1, OK)]
    assert three.handle(command(REG_WRITE_3), 0.0) == [ds.StatusReply(3, OK)]
    assert read(one, "reg_write_pending", 0.5) == 1 and read(two, "reg_write_pending", 0.5) == 0
    assert read(one, "present_position", 0.5) == 2048, "nothing moves before ACTION"
    for servo in (one, two, three):
        assert servo.accepts(command(ACTION)) and servo.handle(command(ACTION), 1.0) == []
    assert read(one, "reg_write_pending", 1.0) == 0
    assert read(one, "present_position", 2.0) == 2000 and read(one, "move_time", 2.0) == 1000
    assert read(three, "present_position", 2.0) == 1524
    assert read(three, "present_position", 3.0) == 1000
    assert read(two, "present_position", 3.0) == 2048, "no REG WRITE: ACTION does nothing"


def test_a_new_reg_write_before_action_replaces_the_old() -> None:
    servo = DsServoDevice(1)
    servo.handle(ds.RegWrite(1, 100, 0), 0.0)
    servo.handle(ds.RegWrite(1, 3000, 0), 0.0)
    servo.handle(ds.Action(), 0.0)
    assert read(servo, "present_position", 5.0) == 3000
    servo.handle(ds.Action(), 5.0)  # nothing pending any more
    assert read(servo, "target_position", 5.0) == 3000


def test_manual_sync_write_moves_each_listed_servo_by_its_own_entry() -> None:
    frame = ds.SyncWrite((ds.SyncTarget(1, 1000, 500), ds.SyncTarget(3, 3000, 0)))
    one, three = DsServoDevice(1), DsServoDevice(3)
    assert one.handle(frame, 0.0) == [] and three.handle(frame, 0.0) == []
    assert read(one, "target_position", 0.0) == 1000 and read(one, "move_time", 0.0) == 500
    assert read(three, "present_position", 1.0) == 3000
    manual = command(SYNC_WRITE_1_3)
    assert one.handle(manual, 2.0) == []
    assert read(one, "present_position", 3.0) == 2000


# --- presets ---------------------------------------------------------------------------------


def test_preset_address_alone_stores_the_position_and_goto_runs_there() -> None:
    servo = DsServoDevice(1)
    move(servo, 1000, 0, 0.0)
    assert write(servo, 0x18, b"", 1.0) == [ds.StatusReply(1, OK)]
    assert read(servo, "preset_2", 1.0) == 1000 and read(servo, "preset_1", 1.0) == 2048
    move(servo, 3000, 0, 1.0)
    write(servo, 0x2C, (1000).to_bytes(2, "big"), 2.0)
    write(servo, 0x3D, b"", 2.0)
    assert read(servo, "present_position", 2.5) == 2000, "in the move time register's 1000 ms"
    assert read(servo, "present_position", 3.0) == 1000
    write(servo, 0x3C, b"", 3.0)
    assert read(servo, "present_position", 4.0) == 2048


# --- status bits and device faults -----------------------------------------------------------


def test_temperature_and_voltage_faults_set_their_bits_in_every_reply() -> None:
    servo = DsServoDevice(1)
    servo.inject_fault("over_temperature", 0.0)
    assert status(servo, 0.0) == ds.ServoStatus.TEMPERATURE
    assert read(servo, "temperature", 0.0) == OVER_TEMPERATURE_C
    servo.inject_fault("under_voltage", 0.0)
    [reply] = write(servo, 0x28, b"\x01", 0.0)
    assert reply.status == ds.ServoStatus.TEMPERATURE | ds.ServoStatus.VOLTAGE
    move(servo, 3000, 0, 0.0)
    assert read(servo, "present_position", 5.0) == 3000, "flags only: the servo still moves"
    servo.reboot(6.0)
    assert status(servo, 6.0) == OK and read(servo, "temperature", 6.0) == AMBIENT_C


def test_stall_trips_after_the_stall_protection_time_and_unloads() -> None:
    servo = DsServoDevice(1)
    move(servo, 3048, 1000, 0.0)
    servo.inject_fault("stall", 0.5)
    assert read(servo, "present_position", 1.0) == 2548, "the jammed shaft stays"
    assert read(servo, "current", 1.0) == CURRENT_MA["straining"]
    assert status(servo, 3.4) == OK, "protection waits its 3 s"
    assert status(servo, 3.5) == ds.ServoStatus.OVERLOAD
    assert read(servo, "torque_enable", 3.5) == 0 and read(servo, "current", 3.5) == 0
    move(servo, 100, 0, 4.0)
    assert read(servo, "present_position", 9.0) == 2548
    [reply] = write(servo, 0x28, b"\x01", 9.0)
    assert reply.status == OK, "switching torque on again clears the trip"
    move(servo, 100, 0, 9.0)
    assert read(servo, "present_position", 12.0) == 100


def test_stall_protection_time_register_sets_the_delay() -> None:
    servo = DsServoDevice(1)
    write(servo, 0x06, b"\x01", 0.0)
    servo.inject_fault("stall", 0.0)
    assert status(servo, 0.9) == OK and status(servo, 1.0) == ds.ServoStatus.OVERLOAD


@pytest.mark.parametrize("fault", ["overload", "over_current"])
def test_overload_trips_at_once(fault: str) -> None:
    servo = DsServoDevice(1)
    move(servo, 3048, 1000, 0.0)
    servo.inject_fault(fault, 0.5)
    assert status(servo, 0.5) == ds.ServoStatus.OVERLOAD
    assert read(servo, "present_position", 2.0) == 2548


# --- reset and reboot ------------------------------------------------------------------------


def _disturb(servo: DsServoDevice, now: float) -> None:
    """Move away, store a preset, change saved and RAM registers, leave a REG WRITE pending."""
    move(servo, 1000, 0, now)
    write(servo, 0x16, b"", now + 1)
    write(servo, 0x0B, (3500).to_bytes(2, "big"), now + 1)
    write(servo, 0x2C, (700).to_bytes(2, "big"), now + 1)
    write(servo, 0x28, b"\x00", now + 1)
    servo.handle(ds.RegWrite(servo.device_id, 3000, 0), now + 1)
    servo.inject_fault("overload", now + 1)


def test_reset_restores_every_factory_value_id_included() -> None:
    servo = DsServoDevice(5)
    _disturb(servo, 0.0)
    assert servo.handle(ds.Reset(5), 2.0) == [ds.StatusReply(5, OK)], "answered as 5"
    assert servo.device_id == 1
    assert read(servo, "preset_1", 2.0) == 2048 and read(servo, "max_angle", 2.0) == 4095
    assert read(servo, "torque_enable", 2.0) == 1 and read(servo, "move_time", 2.0) == 0
    assert read(servo, "reg_write_pending", 2.0) == 0
    assert read(servo, "present_position", 2.0) == read(servo, "target_position", 2.0) == 1000
    servo.handle(ds.Action(), 2.0)
    assert read(servo, "present_position", 5.0) == 1000, "the pending REG WRITE is gone"
    assert not DsServoDevice(3).accepts(command(RESET_1)), "not its id"


def test_reboot_keeps_saved_registers_and_powers_up_the_rest() -> None:
    servo = DsServoDevice(5)
    _disturb(servo, 0.0)
    servo.reboot(2.0)
    assert servo.device_id == 5
    assert read(servo, "preset_1", 2.0) == 1000 and read(servo, "max_angle", 2.0) == 3500
    assert read(servo, "torque_enable", 2.0) == 1 and read(servo, "move_time", 2.0) == 0
    assert read(servo, "reg_write_pending", 2.0) == 0 and status(servo, 2.0) == OK
    assert read(servo, "present_position", 2.0) == read(servo, "target_position", 2.0) == 1000


# --- through SerialSimulator on a pty --------------------------------------------------------

BAUD = 115_200
REPLY_MIN_S = PROTOCOLS["ds_servo"].timing.reply_min_s


@pytest.fixture
def bus() -> Iterator[tuple[SerialSimulator, serial.Serial]]:
    servos = [DsServoDevice(1, position_raw=0x07FF), DsServoDevice(3)]
    with SerialSimulator(ds, servos, baudrate=BAUD) as simulator, serial.Serial(
        simulator.port, BAUD, timeout=10) as host:
        yield simulator, host


def read_frame(servo_id: int, address: int, length: int) -> str:
    return ds.encode(ds.Read(servo_id, address, length)).hex()


def test_wire_manual_ping_and_read(bus) -> None:
    _, host = bus
    assert exchange(host, PING_1, 6) == bytes.fromhex(PING_1_REPLY)
    assert exchange(host, READ_POSITION_1, 8) == bytes.fromhex(READ_POSITION_1_REPLY)


def test_wire_reply_never_beats_wire_time_and_turnaround() -> None:
    baud = 19_200  # wire time dominates: 12 bytes take 6.25 ms
    with SerialSimulator(ds, [DsServoDevice(1)], baudrate=baud) as simulator, serial.Serial(
        simulator.port, baud, timeout=10) as host:
        for frame, reply_bytes in ((PING_1, 6), (READ_POSITION_1, 8)):
            started = time.perf_counter()
            reply = exchange(host, frame, reply_bytes)
            elapsed = time.perf_counter() - started
            assert len(reply) == reply_bytes
            wire = uart_time(len(bytes.fromhex(frame)) + reply_bytes, baud)
            assert elapsed >= wire + REPLY_MIN_S


def test_wire_manual_reg_write_action_and_sync_write(bus, before_proof) -> None:
    simulator, host = bus
    assert exchange(host, REG_WRITE_1, 6) == ds.encode(ds.StatusReply(1, OK))
    assert exchange(host, REG_WRITE_3, 6) == ds.encode(ds.StatusReply(3, OK))
    assert exchange(host, read_frame(1, 0x40, 1), 7)[5] == 1, "REG WRITE pending"
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex(ACTION))
    pending = []
    assert before_proof(simulator, mark, 1, lambda: pending.append(
        exchange(host, read_frame(1, 0x40, 1), 7)[5])) == [], "ACTION was answered"
    assert pending == [0]
    assert exchange(host, read_frame(3, 0x2A, 4), 10)[5:9] == bytes.fromhex("03E807D0")
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex(SYNC_WRITE_1_3))
    goals = []
    assert before_proof(simulator, mark, 1, lambda: goals.append(
        exchange(host, read_frame(1, 0x2A, 2), 8)[5:7])) == [], "SYNC WRITE was answered"
    goals.append(exchange(host, read_frame(3, 0x2A, 2), 8)[5:7])
    assert goals == [bytes.fromhex("07D0")] * 2


def test_wire_broadcast_write_and_read_only_write_get_no_reply(bus, before_proof) -> None:
    simulator, host = bus
    host.write(bytes.fromhex("FF FF FE 04 03 28 00 D2"))  # torque off, every servo
    torque = []
    assert before_proof(simulator, 0, 1, lambda: torque.append(
        exchange(host, read_frame(3, 0x28, 1), 7)[5])) == [], "a broadcast was answered"
    assert torque == [0]
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex("FF FF 01 05 03 38 00 00 BE"))  # the codec discards it
    assert before_proof(simulator, mark, 1, lambda: exchange(host, PING_1, 6)) == []


def test_wire_recorder_keeps_each_received_frame_with_its_wire_time(bus, wait_for) -> None:
    simulator, host = bus
    exchange(host, PING_1, 6)
    host.write(bytes.fromhex(ACTION))
    wait_for(lambda: len(simulator.recorder.received()) >= 2)
    received = simulator.recorder.received()
    assert [(r.frame, r.device_id, r.wire) for r in received] == [
        ("Ping", 1, PING_1.replace(" ", "").lower()), ("Action", None, "fffffe0205fa")]
    assert received[0].end - received[0].start == pytest.approx(uart_time(6, BAUD))
    assert received[1].start >= received[0].end


def test_wire_server_faults_as_the_host_sees_them(
    bus, wait_for, before_proof, next_reply
) -> None:
    simulator, host = bus
    simulator.faults.configure(drop_rate=1.0)
    host.write(bytes.fromhex(PING_1))  # its reply dropped
    host.write(bytes.fromhex(ACTION))  # no reply: once it is in, the ping was dealt with
    wait_for(lambda: len(simulator.recorder.received()) >= 2)
    simulator.faults.configure(drop_rate=0.0)
    assert before_proof(simulator, 0, 2, lambda: exchange(host, PING_1, 6)) == [], "not dropped"
    simulator.faults.configure(bad_checksum_rate=1.0)
    reply = exchange(host, PING_1, 6)
    assert reply[:-1] == bytes.fromhex(PING_1_REPLY)[:-1] and reply[-1] != 0xFC
    simulator.faults.configure(bad_checksum_rate=0.0, garbage_rate=1.0)
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex(PING_1))
    noisy = host.read(len(next_reply(simulator, mark).wire) // 2)
    assert noisy.endswith(bytes.fromhex(PING_1_REPLY)) and len(noisy) > 6
    simulator.faults.configure(garbage_rate=0.0, late_rate=1.0, late_s=0.2)
    started = time.perf_counter()
    assert exchange(host, PING_1, 6) == bytes.fromhex(PING_1_REPLY)
    assert time.perf_counter() - started >= 0.2
    simulator.faults.configure(late_rate=0.0, silent_ids=frozenset({3}))
    mark = len(simulator.recorder.records)
    host.write(ds.encode(ds.Ping(3)))
    replies = []
    assert before_proof(simulator, mark, 1, lambda: replies.append(
        exchange(host, PING_1, 6))) == [], "a silent id answered"
    assert replies == [bytes.fromhex(PING_1_REPLY)]


def test_wire_device_fault_shows_in_the_status_byte_and_reboot_clears_it(bus) -> None:
    simulator, host = bus
    servo_3 = simulator.devices[1]
    servo_3.inject_fault("over_temperature", time.perf_counter())
    assert exchange(host, read_frame(3, 0x3F, 1), 7)[4:6] == bytes([0x04, OVER_TEMPERATURE_C])
    write_time = "FF FF 03 05 03 2C 01 F4 D3"  # move time 500 ms
    assert exchange(host, write_time, 6) == ds.encode(ds.StatusReply(3, ds.ServoStatus(4)))
    assert exchange(host, read_frame(3, 0x2C, 2), 8)[5:7] == b"\x01\xf4"
    servo_3.reboot(time.perf_counter())
    reply = exchange(host, read_frame(3, 0x2C, 2), 8)
    assert reply[4] == 0 and reply[5:7] == b"\x00\x00"


def test_wire_unplug_and_replug_behind_a_link(tmp_path) -> None:
    by_id = tmp_path / "usb-DS-servo-adapter"
    with SerialSimulator(ds, [DsServoDevice(1, position_raw=0x07FF)], baudrate=BAUD,
                         link=PtyLink(str(by_id))) as simulator:
        with serial.Serial(str(by_id), BAUD, timeout=1) as host:
            assert exchange(host, PING_1, 6) == bytes.fromhex(PING_1_REPLY)
            simulator.unplug()
            _wait_for(lambda: not by_id.exists())
            with pytest.raises(serial.SerialException):
                host.read(1)
        simulator.replug()
        _wait_for(by_id.exists)
        with serial.Serial(str(by_id), BAUD, timeout=10) as host:
            assert exchange(host, READ_POSITION_1, 8) == bytes.fromhex(READ_POSITION_1_REPLY)


def _wait_for(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_cli_serves_until_sigterm() -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "busgate.gateway.cli", "sim", "ds_servo", "--ids", "1,2",
         "--baudrate", str(BAUD)],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        first = process.stdout.readline().split()
        assert first[0] == "PORT"
        with serial.Serial(first[1], BAUD, timeout=2) as host:
            assert exchange(host, "FF FF 02 02 01 FA", 6) == bytes.fromhex("FF F5 02 02 00 FB")
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=5) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
