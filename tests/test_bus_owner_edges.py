"""The bus owners' rarely travelled paths, on real ptys and python-can's virtual bus: a CAN
controller gone bus-off, a full CAN transmit queue, a serial write the kernel takes in parts,
an adapter unplugged while a reply is awaited, and stale input flushed before a request.

A full transmit queue (``ENOBUFS``) comes only from SocketCAN, which this machine cannot give
a test (no ``vcan`` module); ``FullQueueBus`` plays it as a python-can interface of its own: a
virtual bus whose ``send`` answers ``ENOBUFS`` as long as the test says the queue is full."""

from __future__ import annotations

import errno
import itertools
import os
import threading
import time
from typing import ClassVar

import can
import pytest

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.errors import BusIOError, BusUnavailableError, DeviceTimeoutError
from busgate.gateway.bus import serial_owner as serial_owner_module
from busgate.gateway.bus.can_owner import CAN_ERR_BUSOFF, LOOK_FRAMES_MAX, CanBusOwner
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.serial_owner import WRITE_TIMEOUT_S, SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.bus.tty_write import DRAIN_MAX_S, left_driver, queued_out
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator

_channels = itertools.count()
CAN_TIMING = link_timing("zlac706_can", 500_000, margin_s=0.05)
LA_TIMING = link_timing("inspire_la", 921_600, margin_s=0.05, gap_s=0.001)


def can_owner(interface: str, channel: str) -> CanBusOwner:
    owner = CanBusOwner(interface, channel, {}, zcan, CAN_TIMING, BusCounters(now()),
                        on_unsolicited=lambda event, when: None)
    owner.open()
    return owner


def speed_write(rpm_raw: int = 0) -> Request:
    return Request.of(zcan, zcan.Write(1, zcan.CanRegister.TARGET_SPEED, rpm_raw))


def test_an_option_python_can_refuses_leaves_the_bus_unavailable_not_a_bug() -> None:
    """Every exception of python-can's open is the owner's to classify (its rule 2): a
    keyword the interface cannot take raises TypeError there."""
    owner = CanBusOwner("virtual", f"edges-options-{next(_channels)}", {"channel": "y"}, zcan,
                        CAN_TIMING, BusCounters(now()), on_unsolicited=lambda event, when: None)
    with pytest.raises(BusUnavailableError, match="cannot open CAN virtual:edges-options-"):
        owner.open()
    assert not owner.is_open


def test_a_look_at_a_flooded_bus_takes_a_bounded_batch() -> None:
    """Frames past what a bus carries: a look ends after ``LOOK_FRAMES_MAX`` of them (the
    runner's turn comes, an e-stop's too), and the next look takes the next batch."""
    channel = f"edges-flood-{next(_channels)}"
    taken = []
    owner = CanBusOwner("virtual", channel, {}, zcan, CAN_TIMING, BusCounters(now()),
                        on_unsolicited=lambda event, when: taken.append(event))
    owner.open()
    flood = can.Bus(interface="virtual", channel=channel)
    try:
        heartbeat = can.Message(arbitration_id=1, data=bytes.fromhex("00fe002000000001"),
                                is_extended_id=False)
        for _ in range(LOOK_FRAMES_MAX * 2 + 10):
            flood.send(heartbeat)
        owner.take_unsolicited()
        assert len(taken) == LOOK_FRAMES_MAX
        owner.take_unsolicited()
        owner.take_unsolicited()
        assert len(taken) == LOOK_FRAMES_MAX * 2 + 10
    finally:
        flood.shutdown()
        owner.close()


def test_a_bus_off_error_frame_closes_the_link(wait_for) -> None:
    channel = f"edges-busoff-{next(_channels)}"
    owner = can_owner("virtual", channel)
    with can.Bus(interface="virtual", channel=channel) as controller:
        controller.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True,
                                    is_extended_id=False, dlc=8, data=bytes(8)))
        with pytest.raises(BusIOError, match="bus-off"):
            for _ in range(100):  # the frame is delivered in its own time
                owner.idle_until(now() + 0.01)
    assert not owner.is_open


class FullQueueBus(can.BusABC):
    """A virtual bus whose transmit queue is full while ``FULL`` holds sends to refuse."""

    FULL: ClassVar[list[int]] = [0]

    def __init__(self, channel: str, **kwargs: object) -> None:
        self._bus = can.Bus(interface="virtual", channel=channel)
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.FULL[0]:
            self.FULL[0] -= 1
            raise can.CanOperationError("No buffer space available", error_code=errno.ENOBUFS)
        self._bus.send(msg, timeout)

    def _recv_internal(self, timeout):
        return self._bus.recv(timeout), False

    def shutdown(self) -> None:
        self._bus.shutdown()
        super().shutdown()


@pytest.fixture
def full_queue_bus(monkeypatch):
    """``FullQueueBus`` registered as interface ``full-queue``, as a python-can plugin's entry
    point would register it (python-can reads those once, at import)."""
    monkeypatch.setitem(can.interfaces.BACKENDS, "full-queue", (__name__, "FullQueueBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES",
                        can.util.VALID_INTERFACES | {"full-queue"})
    channel = f"edges-enobufs-{next(_channels)}"
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as wire:
        yield channel, wire


def test_a_full_transmit_queue_is_waited_out(full_queue_bus) -> None:
    channel, wire = full_queue_bus
    owner = can_owner("full-queue", channel)
    try:
        FullQueueBus.FULL[0] = 3  # refused three times, then taken
        owner.exchange(Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0)))
        sent = wire.recv(timeout=1)
        assert sent is not None and sent.arbitration_id == 0
        assert owner.is_open and owner.counters.frames_out == 1
    finally:
        owner.close()


def test_a_transmit_queue_that_stays_full_fails_the_request_not_the_link(full_queue_bus) -> None:
    channel, wire = full_queue_bus
    owner = can_owner("full-queue", channel)
    try:
        FullQueueBus.FULL[0] = 10**6
        with pytest.raises(DeviceTimeoutError, match="transmit queue full"):
            owner.exchange(speed_write())
        assert owner.is_open and owner.counters.timeouts == 1
        assert wire.recv(timeout=0.05) is None
    finally:
        FullQueueBus.FULL[0] = 0
        owner.close()


class PtyDevice:
    """The far end of a pty, played by the test: what it writes, the owner reads."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        self.port = os.ttyname(self._slave)

    def close(self) -> None:
        os.close(self.master)
        os.close(self._slave)


def serial_owner(port: str) -> SerialBusOwner:
    owner = SerialBusOwner(port, la, LA_TIMING, BusCounters(now()))
    owner.open()
    return owner


def test_a_write_the_kernel_takes_in_parts_is_finished(wait_for) -> None:
    device = PtyDevice()
    owner = serial_owner(device.port)
    try:
        filler = 0
        with pytest.raises(BlockingIOError):  # fill the pty until the kernel takes no more
            while True:
                filler += os.write(owner._serial.fileno(), b"\x00" * 1024)
        frame = Request.of(la, la.FollowCommand(1, 700, reply=False))
        drained = bytearray()

        def drain_later() -> None:
            time.sleep(0.05)
            while len(drained) < filler + len(frame.wire):
                drained.extend(os.read(device.master, 65536))

        reader = threading.Thread(target=drain_later)
        reader.start()
        owner.exchange(frame)
        reader.join(5)
        assert bytes(drained[-len(frame.wire):]) == frame.wire, "the whole frame, in order"
        assert len(drained) == filler + len(frame.wire)
    finally:
        owner.close()
        device.close()


def test_a_port_that_takes_no_more_bytes_fails_the_link_waiting_not_spinning() -> None:
    """A wedged adapter (its far end never reads): the write waits for room, up to its
    timeout, then the link is lost. pyserial's own write spun a core all that while: here
    the thread's CPU over the wait is a small share of it."""
    device = PtyDevice()
    owner = serial_owner(device.port)
    try:
        refused = 0
        while refused < 10:  # fill the pty until the kernel takes no byte more, for a while
            try:
                os.write(owner._serial.fileno(), b"\x00")
                refused = 0
            except BlockingIOError:
                refused += 1
                time.sleep(0.01)
        cpu, started = time.thread_time(), now()
        with pytest.raises(BusIOError, match="write timeout: the port took no more bytes"):
            owner.exchange(Request.of(la, la.FollowCommand(1, 700, reply=False)))
        waited = now() - started
        assert waited >= WRITE_TIMEOUT_S and not owner.is_open
        assert time.thread_time() - cpu < waited / 4, "it waited for room, it did not spin"
    finally:
        owner.close()
        device.close()


def test_a_frame_with_no_reply_frees_the_line_its_wire_time_after_it_left_the_driver(
        monkeypatch) -> None:
    """The gap after a frame that gets no reply counted from the write's return: a USB
    adapter's driver sends a moment later, and the next frame could follow it by less than
    the gap. The exchange now ends the frame's wire time after the driver held none of it
    (``left_driver``, here a stand-in 5 ms after the write); a pty holds nothing back, and it
    ends its wire time after the first look, a moment after the write."""
    device = PtyDevice()
    owner = serial_owner(device.port)
    request = Request.of(la, la.FollowCommand(1, 700, reply=False))
    wire = LA_TIMING.wire_time(request.wire)
    try:
        exchange = owner.exchange(request)
        assert queued_out(owner._serial.fileno()) == 0
        assert exchange.start + wire <= exchange.end <= now() + wire
        asked: list[tuple[int, float]] = []
        monkeypatch.setattr(serial_owner_module, "left_driver",
                            lambda fd, written: asked.append((fd, written)) or written + 0.005)
        exchange = owner.exchange(request)
        assert asked == [(owner._serial.fileno(), exchange.start)]
        assert exchange.end == exchange.start + 0.005 + wire
        with pytest.raises(DeviceTimeoutError):  # nobody answers on this pty
            owner.exchange(Request.of(la, la.ControlCommand(1, la.ControlCode.STATUS)))
        assert len(asked) == 1  # a frame with a reply: its reply says when the line is free
    finally:
        owner.close()
        device.close()


def test_left_driver_is_the_first_look_that_found_the_drivers_queue_empty() -> None:
    """Timing logic, with a stand-in for the driver's queue (no tty on this host holds
    bytes back: a pty's reads empty at once)."""
    written = now()
    assert written <= left_driver(-1, written, lambda fd: 0) <= now()  # the first look's
    late = now() - 0.002  # a thread held up after its write: the look is later, and says so
    assert left_driver(-1, late, lambda fd: 0) >= late + 0.002
    looks: list[float] = []

    def draining(_fd: int) -> int:
        looks.append(now())
        return max(9 - 3 * len(looks), 0)  # 6, 3, then empty at the third look

    left = left_driver(-1, written, draining)
    assert len(looks) == 3 and looks[0] < looks[1] < looks[2] <= left
    stuck = now()
    assert left_driver(-1, stuck, lambda fd: 9) >= stuck + DRAIN_MAX_S  # then it gives up
    reader, writer = os.pipe()
    os.write(writer, b"held")
    assert queued_out(writer) == 0  # no tty: nothing known to be held
    os.close(reader)
    os.close(writer)


def test_an_adapter_unplugged_while_a_reply_is_awaited_closes_the_link(tmp_path) -> None:
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600, link=link) as simulator:
        timing = link_timing("inspire_la", 921_600, margin_s=2.0, gap_s=0.001)
        owner = SerialBusOwner(simulator.port, la, timing, BusCounters(now()))
        owner.open()
        simulator.faults.configure(silent_ids=frozenset({1}))
        threading.Timer(0.1, simulator.unplug).start()
        with pytest.raises(BusIOError):
            owner.exchange(Request.of(la, la.ControlCommand(1, la.ControlCode.STATUS)))
        assert not owner.is_open


def test_stale_input_is_flushed_and_counted_before_a_request() -> None:
    device = PtyDevice()
    owner = serial_owner(device.port)
    status = la.StatusReply(1, 0, 0, 25, 0, 0, la.Fault(0))
    stale = b"\x13\x37\x00" + la.encode(la.StatusReply(2, 0, 0, 25, 0, 0, la.Fault(0)))

    def answer() -> None:
        os.read(device.master, 64)
        time.sleep(0.002)  # well after our frame could have left the wire
        os.write(device.master, la.encode(status))

    try:
        os.write(device.master, stale)
        deadline = time.monotonic() + 5
        while not owner._serial.in_waiting and time.monotonic() < deadline:
            time.sleep(0.001)
        threading.Thread(target=answer).start()
        exchange = owner.exchange(Request.of(la, la.ControlCommand(1, la.ControlCode.STATUS)))
        assert exchange.reply == (status,)
        assert owner.counters.late_replies == 1 and owner.counters.discarded_bytes == 3
    finally:
        owner.close()
        device.close()
