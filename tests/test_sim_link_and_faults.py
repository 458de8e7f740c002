"""The simulators' transport pieces on real ptys with pyserial as the host: the link that can
be unplugged and replugged behind a symlink, the SLCAN adapter as python-can's ``slcan``
interface sees it, and the fault injector's decisions."""

from __future__ import annotations

import os
import threading
import time

import can
import pytest
import serial

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.faults import FaultConfig, FaultInjector
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.slcan import SlcanAdapter


def _read_until(link: PtyLink, size: int, timeout: float = 2.0) -> bytes:
    data, deadline = b"", time.monotonic() + timeout
    while len(data) < size and time.monotonic() < deadline:
        data += link.read()
        time.sleep(0.001)
    return data


def test_host_and_link_exchange_bytes_both_ways() -> None:
    link = PtyLink()
    try:
        with serial.Serial(link.path, 921600, timeout=1) as host:
            host.write(b"\x55\xaa\x01")
            assert _read_until(link, 3) == b"\x55\xaa\x01"
            link.write(b"\xaa\x55")
            assert host.read(2) == b"\xaa\x55"
    finally:
        link.close()


def test_unplug_breaks_the_host_and_replug_moves_the_symlink(tmp_path) -> None:
    by_id = tmp_path / "usb-sim-adapter"
    link = PtyLink(str(by_id))
    first = link.path
    assert os.readlink(by_id) == first
    host = serial.Serial(str(by_id), 115200, timeout=0.2)
    link.want(False)
    assert link.sync() is False
    assert not by_id.exists()
    with pytest.raises(serial.SerialException):
        host.read(1)
    host.close()
    link.want(True)
    assert link.sync() is True
    assert os.readlink(by_id) == link.path
    with serial.Serial(str(by_id), 115200, timeout=1) as again:
        link.write(b"\x01")
        assert again.read(1) == b"\x01"
    link.close()


def test_slcan_adapter_speaks_to_python_can(tmp_path) -> None:
    channel = f"test-slcan-{os.getpid()}"
    adapter = SlcanAdapter(channel).start()
    device_side = can.Bus(interface="virtual", channel=channel)
    host = can.Bus(interface="slcan", channel=adapter.port, bitrate=500_000, sleep_after_open=0)
    try:
        command = bytes.fromhex("00fa00190000003f")
        host.send(can.Message(arbitration_id=0x001, data=command, is_extended_id=False))
        received = device_side.recv(timeout=2)
        assert received is not None and received.arbitration_id == 1
        assert bytes(received.data) == command
        device_side.send(can.Message(arbitration_id=0x001, data=bytes.fromhex("00fb00190000003f"),
                                     is_extended_id=False))
        answer = host.recv(timeout=2)
        assert answer is not None and bytes(answer.data) == bytes.fromhex("00fb00190000003f")
        assert adapter.bitrate == 500_000 and adapter.is_open
    finally:
        host.shutdown()
        device_side.shutdown()
        adapter.stop()


def test_slcan_refuses_what_a_closed_channel_or_bad_line_cannot_do() -> None:
    adapter = SlcanAdapter(f"test-slcan-refuse-{os.getpid()}")
    try:
        assert adapter._execute("t0012aabb") == b"\a", "not open yet"
        assert adapter._execute("O") == b"\a", "no bitrate yet"
        assert adapter._execute("S6") == b"\r" and adapter._execute("O") == b"\r"
        assert adapter._execute("S4") == b"\a", "bitrate is fixed while open"
        assert adapter._execute("t0013aabb") == b"\a", "length and data disagree"
        assert adapter._execute("t00") == b"\a"
        assert adapter._execute("T000000010100") == b"\a", "extended frames are not ours"
        assert adapter._execute("t0012aabb") == b"z\r"
        assert adapter._execute("V").startswith(b"V")
    finally:
        adapter.stop()


def test_fault_injector_extremes_and_repeatability() -> None:
    wire = bytes.fromhex("aa55040101625802c2")
    assert FaultInjector().shape(wire).wire == wire
    assert FaultInjector(FaultConfig(drop_rate=1.0)).shape(wire).wire is None
    corrupted = FaultInjector(FaultConfig(bad_checksum_rate=1.0)).shape(wire).wire
    assert corrupted[:-1] == wire[:-1] and corrupted[-1] != wire[-1]
    noisy = FaultInjector(FaultConfig(garbage_rate=1.0)).shape(wire).wire
    assert noisy.endswith(wire) and 1 <= len(noisy) - len(wire) <= 8
    late = FaultInjector(FaultConfig(late_rate=1.0, late_s=0.2)).shape(wire)
    assert late.wire == wire and late.delay_s == 0.2
    can_reply = FaultInjector(FaultConfig(bad_checksum_rate=1.0, garbage_rate=1.0))
    assert can_reply.shape(wire, checksummed=False).wire == wire

    def decisions(seed: int) -> list:
        injector = FaultInjector(FaultConfig(drop_rate=0.3, garbage_rate=0.3), seed=seed)
        return [injector.shape(wire) for _ in range(50)]

    assert decisions(7) == decisions(7)
    assert decisions(7) != decisions(8)


def test_fault_config_is_checked_and_changeable() -> None:
    with pytest.raises(ValueError, match="drop_rate"):
        FaultConfig(drop_rate=1.5)
    with pytest.raises(ValueError, match="late_s"):
        FaultConfig(late_s=-1)
    injector = FaultInjector()
    injector.configure(silent_ids=frozenset({3}))
    assert injector.config.silent_ids == {3}


class _HeldDevice(InspireLaDevice):
    """An actuator that answers only once the test lets it (its server's thread waits)."""

    def __init__(self, device_id: int, go: threading.Event) -> None:
        super().__init__(device_id)
        self.go = go

    def handle(self, command: object, now: float) -> list[object]:
        self.go.wait(10)
        return super().handle(command, now)


def test_a_reply_meets_the_faults_of_when_its_command_came_in(wait_for) -> None:
    """A command on record has its faults fixed: faults changed while its replies are still
    being made (a loaded host) do not reach them, so a test that sees the command and then
    clears a drop cannot race its own dropped reply."""
    go = threading.Event()
    faults = FaultInjector(FaultConfig(drop_rate=1.0))
    with (
        SerialSimulator(la, [_HeldDevice(1, go)], baudrate=921600, faults=faults) as simulator,
        serial.Serial(simulator.port, 921600, timeout=0.5) as host,
    ):
        host.write(la.encode(la.ControlCommand(1, la.ControlCode.STATUS)))
        wait_for(lambda: simulator.recorder.received())
        faults.configure(drop_rate=0.0)  # the reply is not made yet: the device is held
        go.set()
        host.write(la.encode(la.ControlCommand(1, la.ControlCode.STATUS)))
        assert len(host.read(la.STATUS_REPLY_SIZE)) == la.STATUS_REPLY_SIZE  # the second's
    sent = [r for r in simulator.recorder.records if r.direction == "tx"]
    assert len(sent) == 1, "the first reply went out although it was dropped when it came in"
