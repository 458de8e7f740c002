"""The serial owner at the edges of the line: the UART gap counts from the last byte seen on
it (a late reply included), and a reply that came before its request could have left the wire
is counted as early, with a timeout that says what that points at.

Host side, on real ptys: the LA simulator answering late, and a pty the test plays the device
on itself (answering at once, as an emulator without wire timing does)."""

from __future__ import annotations

import os
import threading
import time
from collections import deque

import pytest

from busgate.codecs import inspire_la as la
from busgate.errors import DeviceTimeoutError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.execution import Execution
from busgate.gateway.scheduler.planner import BusPlanner, Job, Priority, Slot
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator

BAUD = 921_600
GAP_S = 0.001


def owner_on(port: str, baud: int = BAUD, margin_s: float = 0.05) -> SerialBusOwner:
    timing = link_timing("inspire_la", baud, margin_s=margin_s, gap_s=GAP_S)
    owner = SerialBusOwner(port, la, timing, BusCounters(now()))
    owner.open()
    return owner


def status(device_id: int) -> Request:
    return Request.of(la, la.ControlCommand(device_id, la.ControlCode.STATUS), idempotent=True)


def follow_without_reply(position: int) -> Request:
    return Request.of(la, la.FollowCommand(1, position, reply=False))


def test_a_frame_waits_the_gap_after_a_late_reply_it_flushed(tmp_path, wait_for) -> None:
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=BAUD, link=link) as simulator:
        owner = owner_on(simulator.port, margin_s=0.002)
        try:
            simulator.faults.configure(late_rate=1.0, late_s=0.3)  # far past the reply window
            with pytest.raises(DeviceTimeoutError):
                owner.exchange(status(1))
            simulator.faults.configure(late_rate=0.0)
            wait_for(lambda: owner._serial.in_waiting)  # the late reply is on the line now
            asked = now()
            sent = owner.exchange(follow_without_reply(500), at=asked)
            assert owner.counters.late_replies == 1
            # The write started (``start - write_s``) a whole gap after the late reply was
            # read, which was no earlier than ``asked``.
            assert sent.start - sent.write_s - asked >= GAP_S
            # The exchange names when it last read a byte: the late reply, flushed after
            # ``asked``; the gap counted from there is a whole one.
            assert asked <= sent.last_byte_before
            assert sent.start - sent.write_s - sent.last_byte_before >= GAP_S
        finally:
            owner.close()


def test_the_gap_statistic_counts_from_a_stray_byte_read_before_the_write(tmp_path) -> None:
    """Noise on a line quiet for long: the smallest-gap figure is the gap after the noise was
    read (what the next frame waited), not the long quiet since the last exchange."""
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=BAUD, link=link) as simulator:
        owner = owner_on(simulator.port)
        planner = BusPlanner(owner.timing)
        execution = Execution(owner, planner, BusDevices([InspireLaDriver("la1", 1)]), {},
                              state_of=lambda device: None, late_reply_holdoff_s=0.01)

        def poll() -> None:
            execution.run(Slot(status(1), Priority.POLL,
                               Job("la1", deque([status(1)]), Priority.POLL)))

        try:
            poll()
            time.sleep(0.2)
            simulator.link.write(b"\x00\x13")  # two stray bytes towards the host
            time.sleep(0.01)
            owner.counters.smallest_gap_s = None
            poll()
            assert GAP_S <= owner.counters.smallest_gap_s < 0.1
        finally:
            owner.close()


def test_a_quiet_line_costs_no_wait(tmp_path) -> None:
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=BAUD, link=link) as simulator:
        owner = owner_on(simulator.port)
        try:
            owner.exchange(status(1))
            before = owner.counters.late_replies
            owner.exchange(status(1))
            assert owner.counters.late_replies == before
        finally:
            owner.close()


class InstantDevice:
    """Plays an LA actuator on the far end of a pty that answers the moment a request is
    read: what an emulator without wire timing does, or a device at another baud rate (or,
    answering as ``device_id``, another actuator taking a request that was not for it)."""

    def __init__(self, device_id: int = 1) -> None:
        self.device_id = device_id
        self.master, slave = os.openpty()
        self.port = os.ttyname(slave)
        self._slave = slave
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        reply = la.encode(la.StatusReply(self.device_id, 0, 0, 25, 0, 0, la.Fault(0)))
        try:
            while os.read(self.master, 64):
                os.write(self.master, reply)
        except OSError:
            return

    def close(self) -> None:
        os.close(self.master)
        os.close(self._slave)


def test_a_reply_before_the_request_could_have_left_the_wire_is_early() -> None:
    device = InstantDevice()
    # 8 bytes at 300 baud take 267 ms: an answer read sooner cannot be the device's, however
    # long this host was held up before it read it.
    owner = owner_on(device.port, baud=300)
    try:
        with pytest.raises(DeviceTimeoutError, match="baud rate") as timeout:
            owner.exchange(status(1))
        assert "before the request could have left the wire at 300 baud" in str(timeout.value)
        stats = owner.counters.snapshot(now())
        assert stats.early_replies >= 1 and stats.late_replies == 0
    finally:
        owner.close()
        device.close()


@pytest.mark.parametrize("request_to_3", [
    status(3), Request.of(la, la.register_write(3, la.ID, 9)),  # a new id's answer would do
], ids=["status", "set_id"])  # fmt: skip
def test_another_actuators_reply_is_not_taken_for_the_answer(request_to_3) -> None:
    """The owner matches each reply to its request, the one place that does: a driver gets
    only the answer, so actuator 4's status never confirms what was asked of actuator 3."""
    device = InstantDevice(device_id=4)
    owner = owner_on(device.port)
    try:
        with pytest.raises(DeviceTimeoutError):
            owner.exchange(request_to_3)
        stats = owner.counters.snapshot(now())
        assert stats.late_replies >= 1 and stats.early_replies == 0
    finally:
        owner.close()
        device.close()
