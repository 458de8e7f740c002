"""The simulated ZLAC706 (gateway/sim/zlac706.py, zlac706_motor.py): every rule of the manual for
the device on a fake clock, through both front-ends, then end to end on real transports: a
pty with pyserial as the host (RS232), python-can's ``virtual`` bus and an SLCAN adapter with
python-can's ``slcan`` interface (CAN), and the real ``busgate sim`` command.

Frames are the manual's (8.1.1, 8.1.2, 8.2.1, 8.2.2), written as bytes."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time

import can
import pytest
import serial

from busgate.codecs import zlac706_can as can_codec
from busgate.codecs import zlac706_rs232 as rs232_codec
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import ChecksumMismatch
from busgate.codecs.timing import can_time, uart_time
from busgate.codecs.zlac706_common import AlarmFlags, Mode, rpm_from_speed_raw
from busgate.gateway.sim import zlac706
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.slcan import SlcanAdapter
from busgate.gateway.sim.zlac706 import (
    DEFAULT_HEARTBEAT_MS,
    Zlac706CanDevice,
    Zlac706Rs232Device,
)
from busgate.gateway.sim.zlac706_motor import PULSES_PER_REV, Settings
from busgate.schemas.families import PROTOCOLS
from tests.serial_host import exchange

# --- helpers ---------------------------------------------------------------------------------


def can_write(device: Zlac706CanDevice, text: str, now: float, node: int | None = None) -> str:
    """Send one manual frame (``00 FA 00 19 00 00 00 3F``) to ``device``; return its reply."""
    decoder = can_codec.CommandDecoder()
    decoder.feed(CanFrame(device.device_id if node is None else node, bytes.fromhex(text)))
    (command,) = decoder.events()
    assert device.accepts(command)
    (reply,) = device.handle(command, now)
    return can_codec.encode(reply).data.hex(" ").upper()


def rs232_send(device: Zlac706Rs232Device, text: str, now: float) -> bytes:
    """Send the manual's bytes to ``device``; return the bytes of its replies."""
    decoder = rs232_codec.CommandDecoder()
    decoder.feed(bytes.fromhex(text))
    replies = b""
    for command in decoder.events():
        replies += b"".join(rs232_codec.encode(r) for r in device.handle(command, now))
    return replies


def monitor(device: Zlac706Rs232Device, now: float) -> rs232_codec.MonitorReply:
    decoder = rs232_codec.ReplyDecoder()
    decoder.feed(rs232_send(device, "80 00 80", now))
    return rs232_codec.assemble_monitor(decoder.events())


def beat(device: Zlac706CanDevice, now: float) -> tuple[int, float, float]:
    """(position, current A, speed rpm) as the heartbeat reports them at ``now``."""
    device._next_report = None  # a heartbeat now, whatever the schedule
    position, current_speed = device.spontaneous(now)
    return position.position_raw, current_speed.current_a, current_speed.speed_rpm


def rpm(raw: int) -> float:
    return rpm_from_speed_raw(raw)


ENABLE, RELEASE = "00 FA 00 10 00 00 00 1F", "00 FA 00 10 00 00 00 0F"
SPEED_MODE, POSITION_MODE, TORQUE_MODE = (f"00 FA 00 19 00 00 00 {m}" for m in ("2F", "3F", "8F"))
KF_OFF = "00 FA 00 22 00 00 00 00"

# --- CAN: replies ----------------------------------------------------------------------------

MANUAL_CAN_WRITES = [
    RELEASE, ENABLE, SPEED_MODE, POSITION_MODE, TORQUE_MODE,
    "00 FA 00 17 00 00 00 4F", "00 FA 00 17 00 00 00 5F", "00 FA 00 18 00 00 00 6F",
    "00 FA 00 12 00 00 0A 0A", "00 FA 00 14 00 00 0A AA", "00 FA 00 15 00 00 00 7F",
    "00 FA 00 16 00 01 E2 40", "00 FA 00 11 00 00 05 55", "00 FA 00 13 00 00 0A 0A",
    "00 FA 00 20 00 00 0B B8", "00 FA 00 21 00 00 00 01", "00 FA 00 22 00 00 00 01",
    "00 FA 00 23 00 00 13 88", "00 FA 00 24 00 00 01 F4", "00 FA 00 25 00 00 00 00",
    "00 FA 00 26 00 00 01 F4", "00 FA 00 27 00 00 01 F4", "00 FA 00 2D 00 00 1F 40",
    "00 FA 00 08 00 00 05 DC", "00 FA 00 14 00 00 01 11", "00 FA 00 16 FF FE 1D C0",
    "00 FA 00 13 00 00 0A 0B", "00 FA 00 11 FF FF F5 56", "00 FA 00 2D 00 00 27 10",
    "00 FA 00 08 00 00 09 C4",
]


@pytest.mark.parametrize("frame", MANUAL_CAN_WRITES)
def test_can_every_manual_write_is_echoed_with_fb(frame: str) -> None:
    device = Zlac706CanDevice(10)
    assert can_write(device, frame, 0.0) == frame.replace(" FA ", " FB ")


def test_can_unknown_register_gets_ff_and_the_frame_back() -> None:
    device = Zlac706CanDevice(1)
    assert can_write(device, "00 FA 00 33 00 00 12 34", 0.0) == "00 FF 00 33 00 00 12 34"
    assert can_write(device, "05 FA 00 10 00 00 00 1F", 0.0) == "05 FB 00 10 00 00 00 1F"


def test_can_broadcast_is_carried_out_by_every_node_and_answered_db() -> None:
    nodes = [Zlac706CanDevice(1), Zlac706CanDevice(2)]
    decoder = can_codec.CommandDecoder()
    decoder.feed(CanFrame(0, bytes.fromhex("00DA00190000003F")))
    (command,) = decoder.events()
    for node in nodes:
        assert node.accepts(command)
        (reply,) = node.handle(command, 0.0)
        assert str(can_codec.encode(reply)) == "000#00db00190000003f"
        assert node.motor.settings.mode is Mode.POSITION
    assert can_write(nodes[0], "00 DA 00 44 00 00 00 01", 0.0, node=0) == "00 DF 00 44 00 00 00 01"
    to_one = can_codec.Write(1, can_codec.CanRegister.CONTROL_WORD, 0x1F)
    assert nodes[0].accepts(to_one) and not nodes[1].accepts(to_one)


def test_every_register_of_both_codecs_has_its_handler() -> None:
    assert set(zlac706._CAN_WRITES) == {r.address for r in can_codec.REGISTERS}
    assert set(zlac706._RS232_WRITES) == rs232_codec.WRITABLE


def test_can_node_ids_and_options_are_checked() -> None:
    for bad in (0, 110):
        with pytest.raises(ValueError, match="device_id"):
            Zlac706CanDevice(bad)
    with pytest.raises(ValueError, match="heartbeat_ms"):
        Zlac706CanDevice(1, heartbeat_ms=-1)
    with pytest.raises(ValueError):
        Zlac706CanDevice(1, heartbeat_content=3)
    with pytest.raises(TypeError):
        make_devices("zlac706_rs232", [1], heartbeat_ms=50)  # RS232 has no heartbeat
    assert make_devices("zlac706_can", [3], heartbeat_ms=50)[0].heartbeat_s == 0.05


# --- position mode ---------------------------------------------------------------------------


def position_setup(device: Zlac706CanDevice, now: float, *, relative: bool = True) -> None:
    """Manual 8.1.2 steps 1–4: position mode, ramps 1 s, top speed 100 rpm, relative."""
    for frame in (POSITION_MODE, "00 FA 00 12 00 00 0A 0A", "00 FA 00 14 00 00 01 11",
                  f"00 FA 00 17 00 00 00 {'5F' if relative else '4F'}"):
        can_write(device, frame, now)


def test_position_target_before_enable_is_ignored() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0)
    assert can_write(device, "00 FA 00 16 00 01 E2 40", 0.0).startswith("00 FB")
    assert beat(device, 20.0) == (0, 0.0, 0.0)


def test_position_move_follows_the_trapezoid_and_stops_at_the_target() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0)
    can_write(device, ENABLE, 1.0)
    can_write(device, "00 FA 00 16 00 01 E2 40", 1.0)
    top = 0x111 * 3000 / 8192  # 99.97 rpm
    # 1 s from 0 to 1000 rpm: 100 rpm is reached after 0.1 s, and left 0.1 s before the end.
    assert beat(device, 1.05)[2] == pytest.approx(top / 2, abs=1)
    speeds = [beat(device, 1.0 + t / 10)[2] for t in range(1, 80)]
    assert max(speeds) <= top + 1e-9
    # The whole move: the distance at top speed, plus half of each 0.1 s ramp.
    total_s = 123456 / (top * PULSES_PER_REV / 60) + 0.1
    assert beat(device, 1.0 + total_s - 0.05)[2] == pytest.approx(top / 2, abs=1)
    assert beat(device, 1.0 + total_s - 0.01)[0] < 123456
    assert beat(device, 1.0 + total_s + 0.001) == (123456, 0.03, 0.0)
    assert device.motor.commanded_position(1.5) == 123456


def test_position_relative_adds_and_absolute_goes_back_to_the_enable_zero() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0)
    can_write(device, ENABLE, 0.0)
    can_write(device, "00 FA 00 16 00 00 27 10", 0.0)  # +10000
    can_write(device, "00 FA 00 16 00 00 27 10", 0.1)  # +10000 more, while moving
    assert device.motor.commanded_position(0.1) == 20000
    assert beat(device, 10.0)[0] == 20000
    can_write(device, "00 FA 00 17 00 00 00 4F", 10.0)  # absolute
    can_write(device, "00 FA 00 16 FF FF D8 F0", 10.0)  # -10000 from the enable point
    assert beat(device, 20.0)[0] == -10000
    # Released and enabled again: the shaft's place is the new zero (note 6).
    can_write(device, RELEASE, 20.0)
    can_write(device, ENABLE, 20.0)
    assert beat(device, 20.0)[0] == 0


def test_a_target_reversing_a_move_stops_first_then_runs_back() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0, relative=False)
    can_write(device, ENABLE, 0.0)
    can_write(device, "00 FA 00 16 00 01 86 A0", 0.0)  # 100000
    passed = beat(device, 2.0)[0]
    can_write(device, "00 FA 00 16 00 00 00 00", 2.0)  # back to 0
    assert beat(device, 2.05)[0] > passed and beat(device, 2.05)[2] > 0  # still decelerating
    assert beat(device, 2.3)[2] < 0
    assert beat(device, 20.0) == (0, 0.03, 0.0)


def test_max_speed_zero_ramp_and_clamping() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0, relative=False)
    can_write(device, "00 FA 00 12 00 00 00 00", 0.0)  # no ramp: the speed jumps
    can_write(device, "00 FA 00 14 00 00 FF FF", 0.0)  # past 1000 rpm: clamped
    assert device.motor.settings.max_speed == 0x0AAA
    can_write(device, ENABLE, 0.0)
    can_write(device, "00 FA 00 16 00 00 C3 50", 0.0)  # 50000 pulses at 999.76 rpm
    assert beat(device, 0.001)[2] == pytest.approx(rpm(0x0AAA), abs=0.5)
    assert beat(device, 0.31)[0] == 50000


# --- speed mode and the keep-alive -----------------------------------------------------------


def speed_setup(device: Zlac706CanDevice, now: float) -> None:
    """Manual 8.1.2 speed steps 1–3: speed mode, ramps 1 s / 1.1 s, 500 rpm."""
    for frame in (SPEED_MODE, "00 FA 00 13 00 00 0A 0B", "00 FA 00 11 00 00 05 55"):
        can_write(device, frame, now)


def test_speed_preset_starts_at_enable_with_the_ramps() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    assert beat(device, 0.3) == (0, 0.0, 0.0), "a preset speed waits for the enable"
    can_write(device, ENABLE, 1.0)
    assert beat(device, 1.25)[2] == pytest.approx(250, abs=1)  # 1000 rpm per second
    assert beat(device, 1.25)[1] == 2.0  # accelerating
    can_write(device, KF_OFF, 1.4)  # no keep-alive needed from here
    assert beat(device, 1.6)[1:] == (0.3, pytest.approx(rpm(0x555)))
    can_write(device, "00 FA 00 11 FF FF FA AB", 1.6)  # -500 rpm: down through 0 and back up
    assert beat(device, 1.6 + 0.55 / 2)[2] == pytest.approx(250, abs=1)  # 1.1 s per 1000
    assert beat(device, 1.6 + 0.55)[2] == pytest.approx(0, abs=1)
    assert beat(device, 1.6 + 0.55 + 0.25)[2] == pytest.approx(-250, abs=1)  # 1 s per 1000
    assert beat(device, 5.0)[2] == pytest.approx(rpm(-0x555))


def test_disable_releases_the_shaft_where_it_is() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, ENABLE, 0.0)
    can_write(device, "00 FA 00 11 00 00 05 55", 0.4)
    can_write(device, RELEASE, 0.45)
    position = beat(device, 0.45)[0]
    assert position > 0
    assert beat(device, 5.0) == (position, 0.0, 0.0)


def test_keepalive_locks_the_shaft_500_ms_after_the_last_speed_command() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, ENABLE, 0.0)
    for t in (0.4, 0.8, 1.2):  # refreshed within 500 ms: it keeps running
        can_write(device, "00 FA 00 11 00 00 05 55", t)
        assert beat(device, t)[2] > 0
    assert beat(device, 1.69)[2] == pytest.approx(rpm(0x555))
    locked_at = beat(device, 1.7)[0]
    assert beat(device, 3.0) == (locked_at, 0.03, 0.0), "locked: held, not released"
    assert device.motor.status() == AlarmFlags.RUNNING
    can_write(device, "00 FA 00 11 00 00 05 55", 3.0)  # a speed command runs it again
    assert beat(device, 3.4)[2] > 0


def test_keepalive_is_off_with_feed_forward_gain_0() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, KF_OFF, 0.0)
    can_write(device, ENABLE, 0.0)
    assert beat(device, 60.0)[2] == pytest.approx(rpm(0x555))


def test_keepalive_does_not_apply_in_position_mode() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0)
    can_write(device, ENABLE, 0.0)
    can_write(device, "00 FA 00 16 00 01 E2 40", 0.0)
    assert beat(device, 60.0)[0] == 123456


# --- torque mode, origin, mode changes -------------------------------------------------------


def test_torque_mode_current_runs_to_top_speed_and_is_capped_by_rated_current() -> None:
    device = Zlac706CanDevice(1)
    for frame in (TORQUE_MODE, "00 FA 00 08 00 00 05 DC", ENABLE):  # 4.8 A
        can_write(device, frame, 0.0)
    assert beat(device, 0.5)[1:] == (4.8, pytest.approx(500, abs=1))
    assert beat(device, 5.0)[2] == pytest.approx(1000, abs=0.5)
    can_write(device, "00 FA 00 2D 00 00 0B B8", 5.0)  # rated 3000 mA
    assert beat(device, 5.0)[1] == 3.0
    can_write(device, "00 FA 00 08 FF FF FA 24", 5.0)  # -1500: reverse
    assert beat(device, 10.0)[2] == pytest.approx(-1000, abs=0.5)
    can_write(device, RELEASE, 10.0)
    assert beat(device, 10.0)[1:] == (0.0, 0.0)


def test_origin_search_creeps_for_a_z_signal_a_hub_motor_does_not_have() -> None:
    device = Zlac706CanDevice(1)
    position_setup(device, 0.0)
    can_write(device, "00 FA 00 18 00 00 00 6F", 0.0)  # note (9): search, then enable
    assert beat(device, 1.0)[2] == 0.0
    can_write(device, ENABLE, 1.0)
    assert beat(device, 2.0)[2] == pytest.approx(10, abs=0.2)
    assert beat(device, 100.0)[2] == pytest.approx(10, abs=0.2), "no Z signal: it never ends"
    can_write(device, "00 FA 00 16 00 00 00 00", 100.0)  # a target ends it: back to zero
    assert beat(device, 200.0) == (0, 0.03, 0.0)


def test_mode_change_while_running_stops_and_starts_the_new_mode() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, KF_OFF, 0.0)
    can_write(device, ENABLE, 0.0)
    can_write(device, POSITION_MODE, 2.0)
    held = beat(device, 2.0)[0]
    assert beat(device, 3.0) == (held, 0.03, 0.0)
    can_write(device, SPEED_MODE, 3.0)  # back to speed mode: the preset runs again
    assert beat(device, 5.0)[2] == pytest.approx(rpm(0x555))


def test_gains_and_rated_current_are_stored_and_defaults_are_the_manuals() -> None:
    device = Zlac706CanDevice(1)
    assert device.motor.settings == Settings()
    assert (Settings().position_kp, Settings().position_kf, Settings().velocity_kp) == (
        3000, 1, 5000)
    for frame, name, value in (("00 FA 00 20 00 00 0F A0", "position_kp", 4000),
                               ("00 FA 00 27 00 00 00 64", "current_kd", 100),
                               ("00 FA 00 2D 00 00 27 10", "rated_current", 10000)):
        can_write(device, frame, 0.0)
        assert getattr(device.motor.settings, name) == value


# --- heartbeats, alarms, reboot --------------------------------------------------------------


def test_heartbeat_every_interval_with_content_option_0_by_default() -> None:
    device = Zlac706CanDevice(1)
    assert device.heartbeat_s == DEFAULT_HEARTBEAT_MS / 1000 == 0.1
    frames = [(t, device.spontaneous(t)) for t in (x / 1000 for x in range(0, 321, 5))]
    sent = [(t, [str(can_codec.encode(f)) for f in fs]) for t, fs in frames if fs]
    assert [t for t, _ in sent] == pytest.approx([0.0, 0.1, 0.2, 0.3], abs=0.006)
    assert sent[0][1] == ["001#00fe002000000000", "001#00fe002100000000"]


@pytest.mark.parametrize(("content", "registers"), [(1, [0x20]), (2, [0x21])])
def test_heartbeat_content_options(content: int, registers: list[int]) -> None:
    device = Zlac706CanDevice(2, heartbeat_ms=500, heartbeat_content=content)
    assert [can_codec.encode(f).data[3] for f in device.spontaneous(0.0)] == registers
    assert device.spontaneous(0.4) == [] and device.spontaneous(0.5) != []


def test_heartbeat_0_sends_nothing_and_a_late_call_sends_no_burst() -> None:
    assert Zlac706CanDevice(1, heartbeat_ms=0).spontaneous(5.0) == []
    device = Zlac706CanDevice(1)
    device.spontaneous(0.0)
    assert len(device.spontaneous(1.0)) == 2 and device.spontaneous(1.05) == []


@pytest.mark.parametrize(("fault", "code"), [
    ("over_current", 0x02), ("over_voltage", 0x04), ("encoder", 0x08),
    ("over_temperature", 0x10), ("under_voltage", 0x20), ("overload", 0x40)])
def test_alarm_frames_replace_heartbeats_until_alarm_reset(fault: str, code: int) -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, KF_OFF, 0.0)
    can_write(device, ENABLE, 0.0)
    device.inject_fault(fault, 1.0)
    (report,) = device.spontaneous(1.0)
    assert can_codec.encode(report).data.hex(" ").upper() == "00 FF 00 EB " + " ".join(
        [f"{code:02X}"] * 4)
    assert device.motor.speed_raw(1.5) == 0 and device.motor.current_raw(1.5) == 0
    assert device.spontaneous(1.15) == device.spontaneous(1.25) == [report]
    # The manual's warning: an alarm reset while still enabled restarts the motor.
    can_write(device, "00 FA 00 15 00 00 00 7F", 2.0)
    assert beat(device, 4.0)[2] == pytest.approx(rpm(0x555))


def test_alarm_reports_come_every_second_with_heartbeats_off() -> None:
    device = Zlac706CanDevice(1, heartbeat_ms=0)
    device.inject_fault("encoder", 0.0)
    times = [t / 100 for t in range(0, 301) if device.spontaneous(t / 100)]
    assert times == [0.0, 1.0, 2.0, 3.0]
    can_write(device, "00 FA 00 15 00 00 00 7F", 3.0)
    assert device.spontaneous(4.0) == []


def test_enable_during_an_alarm_waits_for_the_reset() -> None:
    device = Zlac706CanDevice(1)
    device.inject_fault("under_voltage", 0.0)
    speed_setup(device, 0.0)
    can_write(device, KF_OFF, 0.0)
    can_write(device, ENABLE, 0.0)
    assert device.motor.speed_raw(2.0) == 0
    can_write(device, "00 FA 00 15 00 00 00 7F", 2.0)
    assert beat(device, 4.0)[2] > 0


def test_unknown_fault_is_refused() -> None:
    with pytest.raises(ValueError, match="over_current"):
        Zlac706CanDevice(1).inject_fault("stall", 0.0)
    with pytest.raises(ValueError):
        Zlac706Rs232Device().inject_fault("melted", 0.0)


def test_reboot_restores_defaults_and_stops_the_motor() -> None:
    device = Zlac706CanDevice(1)
    speed_setup(device, 0.0)
    can_write(device, "00 FA 00 20 00 00 0F A0", 0.0)
    can_write(device, ENABLE, 0.0)
    device.inject_fault("overload", 0.3)
    device.reboot(1.0)
    assert device.motor.settings == Settings()
    assert not device.motor.enabled and device.motor.status() == AlarmFlags(0)
    assert beat(device, 2.0) == (0, 0.0, 0.0)


# --- RS232 -----------------------------------------------------------------------------------

MANUAL_RS232_WRITES = [
    "00 00 01 01", "00 00 00 00", "02 00 C4 C6", "02 00 C0 C2", "02 00 D0 D2", "02 00 C1 C3",
    "4A 00 00 4A", "53 00 00 53", "51 00 00 51", "51 00 01 52", "09 32 32 6D", "1D 00 52 6F",
    "1D 00 A4 C1", "1D 01 48 66", "50 00 00 50", "05 27 10 3C", "50 FF FF 4E", "05 D8 F0 CD",
    "0A 14 14 32", "06 00 88 8E", "06 FF 78 7D", "06 01 11 18", "06 FE EF F3", "06 02 22 2A",
    "06 FD DE E1", "2D 01 F4 22", "2D 03 E8 18", "2D 0B B8 F0", "2D 13 88 C8", "2D 1F 40 8C",
    "08 00 00 08", "08 00 C8 D0", "08 01 F4 FD", "08 03 E8 F3", "08 09 C4 D5",
]


@pytest.mark.parametrize("frame", MANUAL_RS232_WRITES)
def test_rs232_every_manual_write_is_acknowledged_addr_addr(frame: str) -> None:
    assert rs232_send(Zlac706Rs232Device(), frame, 0.0) == bytes.fromhex(frame[:2]) * 2


def test_rs232_position_sequence_of_the_manual_and_the_monitor_reply() -> None:
    device = Zlac706Rs232Device()
    stopped = rs232_send(device, "80 00 80", 0.0)
    assert len(stopped) == 32 and stopped[:4] == bytes.fromhex("80 00 00 80")
    for frame in ("02 00 D0 D2", "1D 00 A4 C1", "00 00 01 01", "50 00 00 50", "05 27 10 3C"):
        rs232_send(device, frame, 0.0)
    moving = monitor(device, 0.5)
    assert moving.commanded_position_raw == 10000 and 0 < moving.feedback_position_raw < 10000
    assert moving.speed_rpm == pytest.approx(60, abs=0.3) and moving.voltage_v == 48
    done = rs232_send(device, "80 00 80", 5.0)
    assert done == bytes.fromhex("80 00 01 81 E1 00 30 11 E2 00 03 E5 E4 00 00 E4"
                                 "E6 00 00 E6 E7 27 10 1E E8 00 00 E8 E9 27 10 20")
    for frame in ("50 FF FF 4E", "05 D8 F0 CD"):  # -10000
        rs232_send(device, frame, 5.0)
    assert monitor(device, 10.0).feedback_position_raw == -10000


def test_rs232_speed_keepalive_is_the_monitor_request_every_second() -> None:
    device = Zlac706Rs232Device()
    for frame in ("02 00 C4 C6", "0A 14 14 32", "06 00 88 8E", "00 00 01 01"):
        rs232_send(device, frame, 0.0)
    for t in (0.9, 1.8, 2.7):
        assert monitor(device, t).speed_rpm > 0
    rs232_send(device, "06 00 88 8E", 3.0)  # a speed write is not the keep-alive on RS232
    assert monitor(device, 3.69).speed_rpm == pytest.approx(49.8, abs=0.1)
    assert monitor(device, 4.8).speed_rpm == 0, "1 s after the last monitor request: locked"
    rs232_send(device, "06 01 11 18", 5.0)  # a speed command after the lock runs it again
    assert monitor(device, 5.5).speed_rpm > 0


def test_rs232_torque_mode_and_stop() -> None:
    device = Zlac706Rs232Device()
    for frame in ("02 00 C1 C3", "08 03 E8 F3", "00 00 01 01"):  # 3.2 A
        rs232_send(device, frame, 0.0)
    assert monitor(device, 0.1).current_a == 3.2
    rs232_send(device, "00 00 00 00", 0.2)
    assert monitor(device, 0.3).alarms == AlarmFlags(0)


def test_rs232_fault_shows_in_the_status_word_until_cleared() -> None:
    device = Zlac706Rs232Device()
    rs232_send(device, "00 00 01 01", 0.0)
    device.inject_fault("over_voltage", 0.1)
    reply = monitor(device, 0.2)
    assert reply.alarms == AlarmFlags.OVER_VOLTAGE and reply.voltage_v == 82
    device.inject_fault("under_voltage", 0.2)
    assert monitor(device, 0.3).alarms == AlarmFlags.OVER_VOLTAGE | AlarmFlags.UNDER_VOLTAGE
    rs232_send(device, "4A 00 00 4A", 0.4)
    assert monitor(device, 0.5).alarms == AlarmFlags.RUNNING


def test_rs232_external_pulse_mode_adds_80_and_ignores_pc_commands() -> None:
    device = Zlac706Rs232Device()
    assert rs232_send(device, "02 00 C0 C2", 0.0) == b"\x02\x02"
    assert rs232_send(device, "00 00 01 01", 0.0) == b"\x00\x00"
    assert monitor(device, 0.1).alarms == AlarmFlags.EXTERNAL_CONTROL
    rs232_send(device, "02 00 D0 D2", 0.2)
    rs232_send(device, "00 00 01 01", 0.2)
    assert monitor(device, 0.3).alarms == AlarmFlags.RUNNING


def test_rs232_reboot_restores_defaults() -> None:
    device = Zlac706Rs232Device(7)
    for frame in ("02 00 C0 C2", "50 00 01 51", "1A 0F A0 C9"):
        rs232_send(device, frame, 0.0)
    device.reboot(1.0)
    assert (device.position_high, device.external) == (0, False)
    assert device.motor.settings == Settings() and device.device_id == 7
    assert device.accepts(rs232_codec.MonitorRequest())


# --- end to end: RS232 on a pty, pyserial as the host ----------------------------------------

BAUD = 19_200  # wire time dominates: a monitor exchange (35 bytes) takes 18 ms


@pytest.fixture
def rs232_line():
    device = Zlac706Rs232Device(1)
    with SerialSimulator(rs232_codec, [device], baudrate=BAUD) as simulator, serial.Serial(
        simulator.port, BAUD, timeout=10
    ) as host:
        yield simulator, device, host


def test_wire_rs232_ack_and_monitor_never_beat_wire_time_and_turnaround(rs232_line) -> None:
    _, _, host = rs232_line
    least = PROTOCOLS["zlac706_rs232"].timing.reply_min_s
    for frame, reply_bytes, replies in (("02 00 D0 D2", 2, 1), ("80 00 80", 32, 8)):
        started = time.perf_counter()
        reply = exchange(host, frame, reply_bytes)
        elapsed = time.perf_counter() - started
        assert len(reply) == reply_bytes
        wire = uart_time(len(bytes.fromhex(frame)) + reply_bytes, BAUD)
        assert elapsed >= wire + replies * least
    assert reply[:4] == bytes.fromhex("80 00 00 80")  # position mode, not enabled


def test_wire_rs232_manual_speed_sequence_runs_the_motor(rs232_line) -> None:
    _, _, host = rs232_line
    for frame in ("02 00 C4 C6", "0A 00 00 0A", "06 01 11 18", "00 00 01 01"):
        assert exchange(host, frame, 2) == bytes.fromhex(frame[:2]) * 2
    decoder = rs232_codec.ReplyDecoder()
    decoder.feed(exchange(host, "80 00 80", 32))
    state = rs232_codec.assemble_monitor(decoder.events())
    assert state.alarms == AlarmFlags.RUNNING and state.speed_rpm == pytest.approx(100, abs=0.1)
    assert exchange(host, "00 00 00 00", 2) == b"\x00\x00"


def test_wire_rs232_recorder_keeps_each_received_frame_with_its_wire_time(rs232_line) -> None:
    simulator, _, host = rs232_line
    exchange(host, "2D 1F 40 8C", 2)
    exchange(host, "80 00 80", 32)
    received = simulator.recorder.received()
    assert [(r.wire, r.frame) for r in received] == [("2d1f408c", "Write"),
                                                      ("800080", "MonitorRequest")]
    assert received[0].end - received[0].start == pytest.approx(uart_time(4, BAUD))
    assert received[1].start >= received[0].end


def test_wire_rs232_server_faults_as_the_host_sees_them(
    rs232_line, wait_for, before_proof, next_reply
) -> None:
    simulator, _, host = rs232_line
    simulator.faults.configure(drop_rate=1.0)
    host.write(bytes.fromhex("4A 00 00 4A"))  # its reply dropped
    host.write(bytes.fromhex("80 00 80"))  # its eight too; once it is in, the write was done
    wait_for(lambda: len(simulator.recorder.received()) >= 2)
    simulator.faults.configure(drop_rate=0.0)
    proof = []
    assert before_proof(simulator, 0, 2, lambda: proof.append(
        exchange(host, "4A 00 00 4A", 2))) == [], "a dropped reply went out"
    assert proof == [b"\x4a\x4a"]
    simulator.faults.configure(late_rate=1.0, late_s=0.3)
    started = time.perf_counter()
    assert exchange(host, "4A 00 00 4A", 2) == b"\x4a\x4a"
    assert time.perf_counter() - started >= 0.3
    simulator.faults.configure(late_rate=0.0, bad_checksum_rate=1.0)
    decoder = rs232_codec.ReplyDecoder()
    decoder.feed(exchange(host, "4A 00 00 4A", 2))
    assert any(isinstance(e, ChecksumMismatch) for e in decoder.events())
    simulator.faults.configure(bad_checksum_rate=0.0, garbage_rate=1.0)
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex("4A 00 00 4A"))
    noisy = host.read(len(next_reply(simulator, mark).wire) // 2)
    assert noisy.endswith(b"\x4a\x4a") and len(noisy) > 2
    simulator.faults.configure(garbage_rate=0.0, silent_ids=frozenset({1}))
    mark = len(simulator.recorder.records)
    host.write(bytes.fromhex("80 00 80"))
    # The line's one device is silent, so no reply can be the proof: a second frame is. The
    # simulator takes frames in order; once it has the second, it had its chance at the first.
    host.write(bytes.fromhex("4A 00 00 4A"))
    wait_for(lambda: sum(r.direction == "rx" for r in simulator.recorder.records[mark:]) >= 2)
    records = simulator.recorder.records
    first = next(i for i, r in enumerate(records) if i >= mark and r.direction == "rx")
    assert [r for r in records[first:] if r.direction == "tx"] == [], "a silent id answered"


def test_wire_rs232_device_fault_and_reboot(rs232_line) -> None:
    _, device, host = rs232_line
    device.inject_fault("encoder", time.perf_counter())
    assert exchange(host, "80 00 80", 32)[:4] == bytes.fromhex("80 00 08 88")
    assert exchange(host, "02 00 C0 C2", 2) == b"\x02\x02"
    device.reboot(time.perf_counter())
    assert exchange(host, "80 00 80", 32)[:4] == bytes.fromhex("80 00 00 80")


def _wait_for(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_wire_rs232_unplug_and_replug_behind_a_link(tmp_path) -> None:
    by_id = tmp_path / "usb-ZLAC706-rs232"
    with SerialSimulator(rs232_codec, [Zlac706Rs232Device()], baudrate=115_200,
                         link=PtyLink(str(by_id))) as simulator:
        with serial.Serial(str(by_id), 115_200, timeout=10) as host:
            assert exchange(host, "00 00 01 01", 2) == b"\x00\x00"
            simulator.unplug()
            _wait_for(lambda: not by_id.exists())
            with pytest.raises(serial.SerialException):
                host.read(1)
        simulator.replug()
        _wait_for(by_id.exists)
        with serial.Serial(str(by_id), 115_200, timeout=10) as host:
            assert exchange(host, "80 00 80", 32)[:4] == bytes.fromhex("80 00 01 81")


# --- end to end: CAN on python-can's virtual bus ---------------------------------------------

_channels = itertools.count()


def channel_name() -> str:
    return f"test-zlac706-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def can_bus():
    """Nodes 1 and 2 without heartbeats on a fresh virtual channel, and the host's bus."""
    channel = channel_name()
    nodes = [Zlac706CanDevice(1, heartbeat_ms=0), Zlac706CanDevice(2, heartbeat_ms=0)]
    simulator = CanSimulator(can_codec, nodes, bus=can.Bus(interface="virtual", channel=channel))
    host = can.Bus(interface="virtual", channel=channel)
    with simulator:
        yield simulator, nodes, host
    host.shutdown()


def send(host: can.BusABC, node: int, text: str) -> None:
    host.send(can.Message(arbitration_id=node, data=bytes.fromhex(text), is_extended_id=False))


def receive(host: can.BusABC, timeout: float = 10.0) -> str | None:
    message = host.recv(timeout=timeout)
    return None if message is None else f"{message.arbitration_id:03x}#{message.data.hex()}"


def test_wire_can_write_is_echoed_no_sooner_than_two_frames_and_turnaround(can_bus) -> None:
    _, _, host = can_bus
    least = 2 * can_time(8, 500_000) + PROTOCOLS["zlac706_can"].timing.reply_min_s
    started = time.perf_counter()
    send(host, 1, "00FA00190000003F")
    assert receive(host) == "001#00fb00190000003f"
    assert time.perf_counter() - started >= least
    send(host, 2, "00FA00330000ABCD")
    assert receive(host) == "002#00ff00330000abcd"


def test_wire_can_broadcast_is_answered_by_every_node(can_bus) -> None:
    _, nodes, host = can_bus
    send(host, 0, "00DA00190000002F")
    assert [receive(host), receive(host)] == ["000#00db00190000002f"] * 2
    assert all(node.motor.settings.mode is Mode.VELOCITY for node in nodes)


def test_wire_can_recorder_and_server_faults(can_bus, wait_for, before_proof) -> None:
    simulator, _, host = can_bus
    send(host, 1, "00FA002D00001F40")
    assert receive(host) == "001#00fb002d00001f40"
    (record,) = simulator.recorder.received()
    assert (record.wire, record.frame, record.device_id) == ("001#00fa002d00001f40", "Write", 1)
    assert record.end - record.start == pytest.approx(can_time(8, 500_000))
    simulator.faults.configure(drop_rate=1.0)
    mark = len(simulator.recorder.records)
    send(host, 1, "00FA002D00001F40")  # its reply dropped
    send(host, 2, "00FA002D00001F40")  # and this one: once it is in, the first was dealt with
    wait_for(lambda: sum(r.direction == "rx" for r in simulator.recorder.records[mark:]) >= 2)
    simulator.faults.configure(drop_rate=0.0)

    def prove() -> None:
        send(host, 2, "00FA00190000002F")
        assert receive(host) == "002#00fb00190000002f"

    assert before_proof(simulator, mark, 2, prove) == [], "a dropped reply went out"
    simulator.faults.configure(late_rate=1.0, late_s=0.2)
    started = time.perf_counter()
    send(host, 1, "00FA002D00001F40")
    assert receive(host) == "001#00fb002d00001f40"
    assert time.perf_counter() - started >= 0.2
    # CAN frames carry the controller's CRC, none of ours: corruption and noise do not apply.
    simulator.faults.configure(late_rate=0.0, bad_checksum_rate=1.0, garbage_rate=1.0)
    send(host, 2, "00FA002D00001F40")
    assert receive(host) == "002#00fb002d00001f40"
    simulator.faults.configure(silent_ids=frozenset({2}))
    mark = len(simulator.recorder.records)
    send(host, 0, "00DA00150000007F")  # broadcast: only node 1 answers
    assert receive(host) == "000#00db00150000007f"

    def prove_node_1() -> None:
        send(host, 1, "00FA002D00001F40")
        assert receive(host) == "001#00fb002d00001f40"

    sent = before_proof(simulator, mark, 1, prove_node_1)
    assert [r.wire for r in sent] == ["000#00db00150000007f"], "the silent node answered"


def test_wire_can_heartbeats_alarm_reports_and_reboot() -> None:
    channel = channel_name()
    node = Zlac706CanDevice(1, heartbeat_ms=20)
    host = can.Bus(interface="virtual", channel=channel)
    with CanSimulator(can_codec, [node], bus=can.Bus(interface="virtual", channel=channel)):
        decoder = can_codec.ReplyDecoder()
        for _ in range(6):
            decoder.feed(CanFrame.parse(receive(host)))
        kinds = [type(event) for event in decoder.events()]
        assert set(kinds) == {can_codec.HeartbeatPosition, can_codec.HeartbeatCurrentSpeed}
        node.inject_fault("encoder", time.perf_counter())
        while (frame := receive(host)).startswith("001#00fe"):  # heartbeats already on their way
            pass
        assert frame == "001#00ff00eb08080808"
        node.reboot(time.perf_counter())
        while (frame := receive(host)) == "001#00ff00eb08080808":
            pass
        assert frame == "001#00fe002000000000"
    host.shutdown()


def test_wire_can_through_an_slcan_adapter_with_python_can_slcan() -> None:
    channel = channel_name()
    adapter = SlcanAdapter(channel).start()
    simulator = CanSimulator(can_codec, [Zlac706CanDevice(5, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    host = can.Bus(interface="slcan", channel=adapter.port, bitrate=500_000, sleep_after_open=0)
    try:
        assert receive(host, 2.0).startswith("005#00fe00")
        send(host, 5, "00FA00100000001F")
        while (frame := receive(host)).startswith("005#00fe"):
            pass
        assert frame == "005#00fb00100000001f"
    finally:
        host.shutdown()
        simulator.stop()
        adapter.stop()


# --- the real CLI ----------------------------------------------------------------------------


def run_cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "busgate.gateway.cli", "sim", *args],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def stop_cli(process: subprocess.Popen) -> None:
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=5) == 0


def test_cli_zlac706_can_heartbeats_over_slcan_until_sigterm() -> None:
    process = run_cli("zlac706_can", "--ids", "1", "--heartbeat-ms", "50")
    try:
        word, port = process.stdout.readline().split()
        assert word == "PORT"
        host = can.Bus(interface="slcan", channel=port, bitrate=500_000, sleep_after_open=0)
        try:
            beats = [receive(host, 2.0) for _ in range(4)]
            assert {frame[:12] for frame in beats} == {"001#00fe0020", "001#00fe0021"}
            send(host, 1, "00FA00190000003F")
            while (frame := receive(host)).startswith("001#00fe"):
                pass
            assert frame == "001#00fb00190000003f"
        finally:
            host.shutdown()
        stop_cli(process)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_cli_zlac706_rs232_serves_until_sigterm() -> None:
    process = run_cli("zlac706_rs232", "--baudrate", "115200")
    try:
        word, port = process.stdout.readline().split()
        assert word == "PORT"
        with serial.Serial(port, 115_200, timeout=2) as host:
            assert exchange(host, "2D 1F 40 8C", 2) == b"\x2d\x2d"
            assert len(exchange(host, "80 00 80", 32)) == 32
        stop_cli(process)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
