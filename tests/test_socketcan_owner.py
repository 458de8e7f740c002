"""The CAN owner on SocketCAN reads python-can's socket itself (``can_owner`` rule 6): every
frame as the kernel lays it out, classified as python-can's messages are.

This host has no SocketCAN (no ``vcan`` module), so ``interface = "socketcan"`` is given the
benchmarks' stand-in, ``unix_can.UnixCanBus``: python-can's bus over a Unix socket whose
datagrams are frames in SocketCAN's layout. The far end is that socket's other end, where the
test writes frames byte by byte as the kernel would give them (a CAN FD frame, a remote
frame's length with no data) and reads what the owner sent."""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import socket
import struct
import threading
import time

import can
import pytest

from busgate.codecs import zlac706_can as zcan
from busgate.codecs.can_frame import CanFrame
from busgate.errors import BusIOError, DeviceTimeoutError
from busgate.gateway.bus import can_owner
from busgate.gateway.bus.can_owner import (
    ARRIVAL_AGE_MAX_S,
    CAN_EFF_FLAG,
    CAN_ERR_BUSOFF,
    CAN_ERR_FLAG,
    CAN_RTR_FLAG,
    CANFD_MTU,
    SO_TIMESTAMPNS,
    TIMESPEC,
    _arrival,
)
from busgate.gateway.bus.clock import now
from tests.benchmarks import unix_can
from tests.test_mutants_bus import (
    ACK,
    HEARTBEAT,
    finished,
    open_can,
    speed_write,
    wait_heard,
)

_channels = itertools.count()


def frame(can_id: int, data: bytes = b"", *, length: int | None = None, fd: bool = False):
    """A frame as a SocketCAN socket gives it: ``struct can_frame`` or ``canfd_frame``."""
    size = 64 if fd else 8
    return struct.pack(f"=IB3x{size}s", can_id, len(data) if length is None else length, data)


def sent_as_socketcan(text: str) -> bytes:
    parsed = CanFrame.parse(text)
    return frame(parsed.arbitration_id, parsed.data)


@contextlib.contextmanager
def socketcan_owner(monkeypatch, **options: object):
    """An owner on ``interface = "socketcan"`` (the stand-in) with ``options``, what it heard,
    and the far end's socket."""
    monkeypatch.setitem(can.interfaces.BACKENDS, unix_can.INTERFACE,
                        (unix_can.__name__, unix_can.UnixCanBus.__name__))
    heard: list = []
    channel = f"owner-{os.getpid()}-{next(_channels)}"
    with unix_can.listening(channel) as server:
        owner = open_can(unix_can.INTERFACE, channel, heard=heard, **options)
        far, _ = server.accept()
    try:
        yield owner, heard, far
    finally:
        owner.close()
        far.close()


@pytest.fixture
def socketcan(monkeypatch):
    """``socketcan_owner``; python-can's ``recv`` fails the test if the owner reads through
    it."""

    def not_through_python_can(*_: object, **__: object):
        raise AssertionError("the owner read SocketCAN through python-can's recv")

    monkeypatch.setattr(unix_can.UnixCanBus, "recv", not_through_python_can)
    with socketcan_owner(monkeypatch) as owner_heard_far:
        yield owner_heard_far


def test_frames_are_read_and_classified_from_socketcans_own_bytes(socketcan):
    owner, heard, far = socketcan
    data = CanFrame.parse(HEARTBEAT).data
    for raw in (
        frame(1 | CAN_EFF_FLAG, data),  # a heartbeat's bytes under a 29-bit identifier
        frame(1 | CAN_RTR_FLAG, length=8),  # a remote frame: a length, no data
        frame(1, data[:7]),  # too short for any reply
        frame(0x801, data),  # no flag, yet past 11 bits: no standard identifier
        frame(1, bytes(12), fd=True),  # a CAN FD frame: no classic frame carries 12 bytes
        frame(CAN_ERR_FLAG | 0x04, bytes(8)),  # an error frame: a controller problem
        sent_as_socketcan(HEARTBEAT),
    ):
        far.send(raw)
    finished(lambda: wait_heard(owner, heard, 1))
    assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
    counters = owner.counters
    assert (counters.frames_in, counters.bytes_in) == (6, 8 + 0 + 7 + 8 + 12 + 8)
    assert counters.discarded_bytes == 8 + 0 + 7 + 8 + 12
    assert owner.is_open

    far.send(frame(CAN_ERR_FLAG | CAN_ERR_BUSOFF, bytes(8)))
    with pytest.raises(BusIOError, match="controller is bus-off"):
        finished(lambda: wait_heard(owner, heard, 2))
    assert not owner.is_open


def test_a_reply_awaited_on_the_socket_ends_the_exchange(socketcan):
    owner, heard, far = socketcan
    request = speed_write()
    sent: list[bytes] = []

    def node() -> None:  # node 1: a heartbeat, then its answer
        sent.append(far.recv(CANFD_MTU))
        far.send(sent_as_socketcan(HEARTBEAT))
        far.send(sent_as_socketcan(ACK))

    answering = threading.Thread(target=node, daemon=True)
    answering.start()
    exchange = finished(lambda: owner.exchange(request))
    answering.join(5)
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
    can_id, length, data = struct.unpack("=IB3x8s", sent[0])
    assert (can_id, data[:length]) == (1, request.wire.data)  # standard, no flags


def test_a_silent_node_times_out_on_the_socket_at_the_end_of_its_window(socketcan):
    """The wait for a reply is a wait on the socket, bounded by the reply's window: a node
    that never answers is a timeout, its frame having gone, the link kept."""
    owner, _, far = socketcan
    request = speed_write()
    started = now()
    with pytest.raises(DeviceTimeoutError, match="no reply from node 1"):
        finished(lambda: owner.exchange(request))
    _, latest = owner.timing.reply_window(request)
    assert now() - started >= latest
    assert far.recv(CANFD_MTU) and owner.is_open and owner.counters.timeouts == 1


def test_a_frame_nobody_asked_for_is_dated_by_its_arrival_not_by_the_look(socketcan):
    owner, heard, far = socketcan
    tapped: list[tuple] = []
    owner.tap = tapped.append  # as the flight recorder takes every frame
    before = now()
    far.send(sent_as_socketcan(HEARTBEAT))
    time.sleep(0.1)  # the look comes later, as an idle look comes up to idle_batch_s later
    looked = now()
    owner.take_unsolicited()
    [(event, arrival)] = heard
    assert event == zcan.HeartbeatPosition(1, 7)
    assert before - 0.001 <= arrival < looked - 0.05
    assert tapped == [(arrival, "rx", CanFrame.parse(HEARTBEAT).data, 1)]


def test_an_exchange_ends_when_its_reply_came_not_when_its_thread_took_it(
    socketcan, monkeypatch
):
    owner, _, far = socketcan
    replied: list[float] = []

    def node() -> None:  # node 1 answers at once; the owner's thread wakes 50 ms late
        far.recv(CANFD_MTU)
        far.send(sent_as_socketcan(ACK))
        replied.append(now())

    class LateSelect:
        @staticmethod
        def select(*args):
            ready = select.select(*args)
            time.sleep(0.05)
            return ready

    monkeypatch.setattr(can_owner, "select", LateSelect)
    answering = threading.Thread(target=node, daemon=True)
    answering.start()
    exchange = finished(lambda: owner.exchange(speed_write()))
    answering.join(5)
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert exchange.start < exchange.end < replied[0] + 0.02


def test_no_frame_is_dated_before_the_frame_before_it(socketcan):
    owner, _, _ = socketcan
    first = owner._date(None)  # dated when taken
    assert owner._date(first - 0.5) == first  # a receive time before it: dated with it
    assert owner._date(first + 0.001) == first + 0.001


def receive_time(wall_s: float, level: int = socket.SOL_SOCKET, kind: int = SO_TIMESTAMPNS):
    """``recvmsg``'s ancillary data carrying a frame's receive time ``wall_s``."""
    seconds = int(wall_s)
    return [(level, kind, TIMESPEC.pack(seconds, int((wall_s - seconds) * 1e9)))]


def test_a_receive_time_that_cannot_be_right_leaves_the_frame_dated_when_taken():
    assert now() - 0.21 < _arrival(receive_time(time.time() - 0.2)) < now() - 0.19
    assert _arrival([]) is None  # the socket was not asked for receive times
    assert _arrival(receive_time(time.time(), kind=SO_TIMESTAMPNS + 1)) is None
    assert _arrival(receive_time(time.time(), level=socket.SOL_SOCKET + 1)) is None
    assert _arrival([(socket.SOL_SOCKET, SO_TIMESTAMPNS, b"\0" * 4)]) is None  # cut short
    assert _arrival(receive_time(time.time() + 0.5)) is None  # the wall clock was set back
    assert _arrival(receive_time(time.time() - ARRIVAL_AGE_MAX_S - 0.5)) is None  # or on


def test_a_socket_whose_far_end_is_gone_is_a_lost_link(socketcan):
    owner, heard, far = socketcan
    far.close()
    with pytest.raises(BusIOError, match=r": the interface's socket was closed$"):
        finished(lambda: wait_heard(owner, heard, 1))
    assert not owner.is_open


def test_a_bus_given_filters_is_read_through_python_can_which_applies_them(monkeypatch):
    """python-can filters in software where the kernel does not (here: the stand-in has no
    kernel filters), so a filtered bus is not read from its socket."""
    only_node_2 = [{"can_id": 2, "can_mask": 0x7FF}]
    with socketcan_owner(monkeypatch, can_filters=only_node_2) as (owner, heard, far):
        data = CanFrame.parse(HEARTBEAT).data
        far.send(frame(1, data))  # node 1: filtered out
        far.send(frame(2, data))
        finished(lambda: wait_heard(owner, heard, 1))
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(2, 7)]
