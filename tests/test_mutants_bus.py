"""What mutation testing (``python tools/mutation/run.py bus``) found the bus tests leaving open,
at the level of each owner's promise: what an exchange puts on the wire, returns and raises
(and names), what every counter counts, where a reply window starts and ends, what is early,
how idle time is spent, how python-can's and pyserial's failures are classified, what is
flushed before a request and how long a talking line is waited on.

The far ends are real: python-can's virtual bus, a pty played by the test as an SLCAN adapter
or as a serial device. Where a python-can failure cannot be had from the virtual bus (a send
or a receive that raises, a shutdown that fails), ``ScriptedBus`` plays it: a python-can
interface of its own, over the virtual bus, that raises what the test put in its script.
The owners' own timing (reply windows, early replies, the idle batches, a timed send, the
transmit back-off, the quiet wait) runs on a fake clock, which the modules take by name; the
fake clock sometimes plays the device too (what comes at a given moment of the window). No
duration is measured: an idle wait returning at or after its deadline is an order of clock
readings. An owner that would hang is run on a thread the test waits for with a generous
deadline."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import math
import os
import select
import struct
import termios
import threading
from collections.abc import Callable
from typing import ClassVar

import can
import pytest

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs import zlac706_rs232 as zrs232
from busgate.codecs.can_frame import CanFrame
from busgate.errors import BusIOError, BusUnavailableError, DeviceTimeoutError
from busgate.gateway.bus import can_owner as can_owner_module
from busgate.gateway.bus import owner as owner_module
from busgate.gateway.bus import serial_owner as serial_owner_module
from busgate.gateway.bus.can_owner import (
    PRECISE_WAIT_S,
    CanBusOwner,
)
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.owner import RX, TX
from busgate.gateway.bus.port_access import describe_open_error
from busgate.gateway.bus.request import LinkTiming, Request
from busgate.gateway.bus.serial_owner import QUIET_WAIT_MAX_S, SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing

_channels = itertools.count()

#: A reply window far longer than any test waits: replies come when the test sends them.
CAN_TIMING = link_timing("zlac706_can", 500_000, margin_s=2.0)
#: A silent node costs little.
CAN_QUICK = link_timing("zlac706_can", 500_000, margin_s=0.01)


def finished(call: Callable[[], object], within: float = 5.0) -> object:
    """``call()``'s result (or its exception, raised here) once it returns; the test fails if
    it has not returned ``within`` seconds (an owner that would wait for ever)."""
    outcome: list = []

    def run() -> None:
        try:
            outcome.append((True, call()))
        except BaseException as exc:  # handed to the test's thread
            outcome.append((False, exc))

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(within)
    assert outcome, f"still waiting after {within} s"
    ok, value = outcome[0]
    if not ok:
        raise value
    return value


class FakeClock:
    """A ``perf_counter`` that moves only when the owner waits (or the test says)."""

    def __init__(self, start: float = 1000.0) -> None:
        self.t = start
        self.pauses: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep_until(self, deadline: float, **_: object) -> float:
        self.t = max(self.t, deadline)
        return self.t

    def pause(self, seconds: float) -> bool:
        self.pauses.append(seconds)
        self.t += seconds
        return False


@pytest.fixture
def fake_clock(monkeypatch) -> FakeClock:
    """The CAN owner's clock, its precise wait and its idle pause, all on one fake clock."""
    clock = FakeClock()
    monkeypatch.setattr(can_owner_module, "now", clock)
    monkeypatch.setattr(can_owner_module, "sleep_until", clock.sleep_until)
    monkeypatch.setattr(owner_module, "now", clock)
    monkeypatch.setattr(owner_module, "_sleep", clock.pause)
    return clock


# -- CAN: the owner on python-can's virtual bus ----------------------------------------------


class Node:
    """The far end of a virtual CAN channel, played by the test."""

    def __init__(self, channel: str, **options: object) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, **options)

    def send(self, text: str, **flags: object) -> None:
        frame = CanFrame.parse(text)
        self.bus.send(
            can.Message(
                arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False, **flags
            )
        )

    def answer(self, *texts: str) -> threading.Thread:
        """Once a frame comes, send ``texts`` (on a thread of its own)."""

        def respond() -> None:
            if self.bus.recv(timeout=10) is not None:
                for text in texts:
                    self.send(text)

        thread = threading.Thread(target=respond, daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        self.bus.shutdown()


@pytest.fixture
def channel() -> str:
    return f"mutants-bus-{next(_channels)}"


@pytest.fixture
def node(channel):
    node = Node(channel)
    yield node
    node.close()


def open_can(
    interface: str, channel: str, timing: LinkTiming = CAN_TIMING, heard=None, **options: object
) -> CanBusOwner:
    heard = [] if heard is None else heard
    owner = CanBusOwner(
        interface,
        channel,
        options,
        zcan,
        timing,
        BusCounters(0.0),
        on_unsolicited=lambda event, when: heard.append((event, when)),
    )
    owner.open()
    return owner


def speed_write(node_id: int = 1) -> Request:
    return Request.of(zcan, zcan.Write(node_id, zcan.CanRegister.TARGET_SPEED, 0))


ACK = "001#00fb001100000000"  # node 1's answer to speed_write()
HEARTBEAT = "001#00fe002000000007"  # node 1 at position 7


def test_a_silent_node_times_out_by_name_each_time_and_the_link_stays(channel, node):
    owner = open_can("virtual", channel, CAN_QUICK)
    try:
        for _ in range(2):
            with pytest.raises(DeviceTimeoutError) as timeout:
                finished(lambda: owner.exchange(speed_write()))
            assert str(timeout.value) == f"no reply from node 1 on virtual:{channel}"
            assert timeout.value.device_id == 1
        counters = owner.counters
        assert (counters.timeouts, counters.frames_out, counters.bytes_out) == (2, 2, 16)
        assert owner.is_open
    finally:
        owner.close()


def test_a_reply_ends_the_exchange_and_what_came_before_it_is_unsolicited(channel, node):
    heard = []
    owner = open_can("virtual", channel, heard=heard)
    try:
        request = speed_write()
        node.answer(HEARTBEAT, ACK)
        before = now()
        exchange = finished(lambda: owner.exchange(request))
        assert exchange.request is request and before <= exchange.start <= exchange.end <= now()
        assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
        assert before <= heard[0][1] <= now()
        counters = owner.counters
        assert (counters.frames_in, counters.bytes_in, counters.discarded_bytes) == (2, 16, 0)
    finally:
        owner.close()


def test_a_request_goes_on_the_wire_as_a_standard_frame_with_its_id_and_data(channel, node):
    owner = open_can("virtual", channel, CAN_QUICK)
    try:
        request = speed_write(5)
        with pytest.raises(DeviceTimeoutError):
            finished(lambda: owner.exchange(request))
        sent = node.bus.recv(timeout=5)
        assert (sent.arbitration_id, bytes(sent.data)) == (5, request.wire.data)
        assert not sent.is_extended_id and not sent.is_remote_frame
    finally:
        owner.close()


def test_a_frame_without_a_reply_holds_the_line_for_its_wire_time(channel, node):
    owner = open_can("virtual", channel)
    try:
        request = Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0))  # all nodes
        assert request.expected is None
        before = now()
        exchange = finished(lambda: owner.exchange(request))
        assert exchange.request is request and before <= exchange.start <= now()
        assert exchange.reply == ()
        assert exchange.end == exchange.start + CAN_TIMING.wire_time(request.wire)
        assert node.bus.recv(timeout=5).arbitration_id == 0
    finally:
        owner.close()


def test_frames_the_decoder_cannot_use_are_counted_and_never_taken(channel, node):
    heard = []
    owner = open_can("virtual", channel, heard=heard)
    try:
        node.bus.send(
            can.Message(arbitration_id=1, data=bytes.fromhex(HEARTBEAT[4:]), is_extended_id=True)
        )  # a heartbeat's bytes, 29-bit id
        node.bus.send(
            can.Message(arbitration_id=1, is_remote_frame=True, dlc=8, is_extended_id=False)
        )
        node.bus.send(
            can.Message(arbitration_id=2, data=bytes.fromhex(HEARTBEAT[4:]), is_extended_id=True)
        )
        node.send("001#00fe0020000000")  # 7 bytes
        node.send("001#00fe00200000")  # 6 bytes
        node.send(HEARTBEAT)
        finished(lambda: wait_heard(owner, heard, 1))
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
        counters = owner.counters
        assert counters.discarded_bytes == 8 + 0 + 8 + 7 + 6
        assert (counters.frames_in, counters.bytes_in) == (6, 8 + 0 + 8 + 7 + 6 + 8)
    finally:
        owner.close()


def wait_heard(owner: CanBusOwner, heard: list, count: int) -> None:
    while len(heard) < count:
        owner.idle_until(now() + 0.01)


def test_an_error_frame_other_than_bus_off_leaves_the_link(channel, node):
    heard = []
    owner = open_can("virtual", channel, heard=heard)
    try:
        node.bus.send(
            can.Message(
                arbitration_id=0x04, is_error_frame=True, dlc=8, data=bytes(8), is_extended_id=False
            )
        )  # controller problem
        node.send(HEARTBEAT)
        finished(lambda: wait_heard(owner, heard, 1))
        assert owner.is_open and owner.counters.frames_in == 1
        node.bus.send(
            can.Message(
                arbitration_id=0x40, is_error_frame=True, dlc=8, data=bytes(8), is_extended_id=False
            )
        )
        with pytest.raises(BusIOError) as lost:
            finished(lambda: wait_heard(owner, heard, 2))
        assert str(lost.value) == f"CAN virtual:{channel}: controller is bus-off"
        assert not owner.is_open
    finally:
        owner.close()


def test_a_closed_owner_says_so_by_name(channel):
    owner = open_can("virtual", channel)
    owner.close()
    with pytest.raises(BusIOError) as closed:
        finished(lambda: owner.exchange(speed_write()))
    assert str(closed.value) == f"CAN virtual:{channel} is not open"


def test_an_interface_that_cannot_be_opened_is_unavailable_by_name():
    owner = CanBusOwner(
        "no-such-interface",
        "can9",
        {},
        zcan,
        CAN_TIMING,
        BusCounters(0.0),
        on_unsolicited=lambda event, when: None,
    )
    with pytest.raises(BusUnavailableError) as refused:
        owner.open()
    assert str(refused.value).startswith("cannot open CAN no-such-interface:can9: ")
    assert not owner.is_open


def test_the_interfaces_options_reach_python_can(channel, node):
    """``receive_own_messages`` passed through: the owner hears its own frame (a write,
    which is no node reply: discarded)."""
    owner = open_can("virtual", channel, receive_own_messages=True)
    try:
        finished(
            lambda: owner.exchange(
                Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0))
            )
        )
        finished(lambda: wait_counted(owner, lambda c: c.frames_in >= 1))
        assert (owner.counters.frames_in, owner.counters.discarded_bytes) == (1, 8)
    finally:
        owner.close()


def wait_counted(owner: CanBusOwner, reached: Callable[[BusCounters], bool]) -> None:
    while not reached(owner.counters):
        owner.idle_until(now() + 0.01)


def test_a_recipient_that_takes_no_more_fails_the_send_instead_of_blocking(channel):
    """A virtual recipient with a one-frame queue it never reads: python-can's ``send``
    waits its timeout, then fails; the owner does not wait for ever."""
    full = Node(channel, rx_queue_size=1)
    owner = open_can("virtual", channel)
    try:
        request = Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0))
        finished(lambda: owner.exchange(request))
        with pytest.raises(BusIOError):
            finished(lambda: owner.exchange(request))
        assert not owner.is_open
    finally:
        owner.close()
        full.close()


# -- CAN: idle time --------------------------------------------------------------------------


def test_idling_takes_in_what_comes_and_lasts_until_its_deadline(channel, node):
    heard = []
    owner = open_can("virtual", channel, heard=heard)
    try:
        node.send(HEARTBEAT)
        deadline = now() + 0.1
        finished(lambda: owner.idle_until(deadline))
        assert now() >= deadline
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
    finally:
        owner.close()


def test_idling_pauses_in_batches_and_ends_at_its_deadline_not_later(channel, node):
    owner = open_can("virtual", channel)
    pauses = []

    def pause(seconds: float) -> bool:
        pauses.append(seconds)
        if len(pauses) >= 1000:
            return True  # the deadline never ended it: stop here, and fail below
        threading.Event().wait(seconds)
        return False

    try:
        deadline = now() + 0.05
        finished(lambda: owner.idle_until(deadline, pause))
        assert 1 <= len(pauses) < 1000 and now() >= deadline
        assert all(0 < p <= CanBusOwner.idle_batch_s for p in pauses)
    finally:
        owner.close()


def test_new_work_ends_an_idle_wait_at_once(channel, node):
    owner = open_can("virtual", channel)
    pauses = []
    try:
        finished(lambda: owner.idle_until(now() + 1.0, lambda s: pauses.append(s) or True))
        assert pauses == [CanBusOwner.idle_batch_s]
    finally:
        owner.close()


def test_an_idle_wait_to_now_pauses_not_at_all(channel, node, fake_clock):
    owner = open_can("virtual", channel)
    pauses = []
    try:
        finished(lambda: owner.idle_until(fake_clock(), lambda s: pauses.append(s) or True))
        assert pauses == []
    finally:
        owner.close()


def test_a_timed_send_idles_until_just_before_its_moment_and_goes_at_it(channel, node, fake_clock):
    heard = []
    owner = open_can("virtual", channel, heard=heard)
    try:
        node.send(HEARTBEAT)
        at = fake_clock() + 0.05
        request = Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0))
        exchange = finished(lambda: owner.exchange(request, at=at))
        assert exchange.start == at
        assert sum(fake_clock.pauses) == pytest.approx(0.05 - PRECISE_WAIT_S)
        assert all(0 < p <= CanBusOwner.idle_batch_s for p in fake_clock.pauses)
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]
    finally:
        owner.close()


# -- CAN: python-can's failures, classified --------------------------------------------------


class ScriptedBus(can.BusABC):
    """The virtual bus, with what ``send``, ``recv`` and ``shutdown`` raise next taken from
    ``SCRIPT``; each ``send`` first runs ``ON_SEND`` with its timeout (a fake clock's wait)."""

    SCRIPT: ClassVar[dict[str, list[BaseException]]] = {"send": [], "recv": [], "shutdown": []}
    ON_SEND: ClassVar[list[Callable[[float | None], None]]] = []

    def __init__(self, channel: str, **kwargs: object) -> None:
        self._bus = can.Bus(interface="virtual", channel=channel)
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        for hook in self.ON_SEND:
            hook(timeout)
        if self.SCRIPT["send"]:
            raise self.SCRIPT["send"].pop(0)
        self._bus.send(msg, timeout)

    def _recv_internal(self, timeout):
        if self.SCRIPT["recv"]:
            raise self.SCRIPT["recv"].pop(0)
        return self._bus.recv(timeout), False

    def shutdown(self) -> None:
        self._bus.shutdown()
        super().shutdown()
        if self.SCRIPT["shutdown"]:
            raise self.SCRIPT["shutdown"].pop(0)


@pytest.fixture
def scripted(monkeypatch, channel, node):
    """``ScriptedBus`` registered as interface ``scripted`` (as a python-can plugin's entry
    point would register it), its script empty; the owner on it and the node at its far end."""
    monkeypatch.setitem(can.interfaces.BACKENDS, "scripted", (__name__, "ScriptedBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"scripted"})
    for steps in ScriptedBus.SCRIPT.values():
        steps.clear()
    ScriptedBus.ON_SEND.clear()
    heard: list = []
    owner = open_can("scripted", channel, heard=heard)
    yield owner, node, ScriptedBus.SCRIPT, heard
    owner.close()
    ScriptedBus.ON_SEND.clear()
    for steps in ScriptedBus.SCRIPT.values():
        steps.clear()


class DescriptorBus(ScriptedBus):
    """The scripted bus with a descriptor that never says a frame is there (a pipe nobody
    writes, ``PIPE``), whatever the virtual bus behind it holds."""

    PIPE: ClassVar[list[int]] = []

    def fileno(self) -> int:
        return self.PIPE[0]


@pytest.mark.parametrize(("interface", "taken"), [("socketcan", True), ("serial", False)])
def test_a_look_asks_the_descriptor_first_only_where_a_look_could_wait(
    monkeypatch, channel, node, interface, taken
):
    """SocketCAN's ``recv(timeout=0)`` never waits: a look reads, with no ``select`` a frame
    before it. A serial adapter's can wait out its serial timeout: its descriptor is asked
    first, and one that says nothing is there is believed."""
    read_end, write_end = os.pipe()
    monkeypatch.setattr(DescriptorBus, "PIPE", [read_end])
    monkeypatch.setitem(can.interfaces.BACKENDS, interface, (__name__, "DescriptorBus"))
    heard: list = []
    owner = open_can(interface, channel, heard=heard)
    try:
        node.send(HEARTBEAT)  # queued at once behind the descriptor
        finished(lambda: owner.idle_until(0.0))  # a deadline long past: one look, no wait
        assert [event for event, _ in heard] == ([zcan.HeartbeatPosition(1, 7)] if taken else [])
    finally:
        owner.close()
        os.close(read_end)
        os.close(write_end)


def test_a_look_at_a_quiet_bus_asks_it_once(channel, node):
    """A look with nothing there (a bus whose looks never wait: python-can's ``virtual``)
    ends at the first empty answer, and one that finds frames takes them, then asks once
    more: it does not ask again up to its bound of frames (``LOOK_FRAMES_MAX``)."""
    owner = open_can("virtual", channel)
    asked: list = []
    take = owner._take
    owner._take = lambda timeout: asked.append(timeout) or take(timeout)
    try:
        finished(owner.take_unsolicited)
        assert asked == [0]
        node.send(HEARTBEAT)
        node.send(HEARTBEAT)
        asked.clear()
        finished(owner.take_unsolicited)
        assert asked == [0, 0, 0]
    finally:
        owner.close()


class DrainedBus(DescriptorBus):
    """The descriptor bus as a serial adapter's is: readable while a frame waits (a byte in
    ``PIPE`` a frame), each frame's byte read off it by the ``recv`` that takes the frame."""

    def _recv_internal(self, timeout):
        message, filtered = super()._recv_internal(timeout)
        if message is not None:
            os.read(self.PIPE[0], 1)
        return message, filtered


def test_a_look_at_an_adapter_whose_descriptor_says_a_frame_waits_takes_it(
    monkeypatch, channel, node
):
    read_end, write_end = os.pipe()
    monkeypatch.setattr(DescriptorBus, "PIPE", [read_end])
    monkeypatch.setitem(can.interfaces.BACKENDS, "serial", (__name__, "DrainedBus"))
    heard: list = []
    owner = open_can("serial", channel, heard=heard)
    try:
        for _ in range(2):
            node.send(HEARTBEAT)
            os.write(write_end, b"x")
        finished(lambda: owner.idle_until(0.0))  # one look: both taken, then none is there
        assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)] * 2
    finally:
        owner.close()
        os.close(read_end)
        os.close(write_end)


def full_queue(message: str = "No buffer space available", code: int | None = errno.ENOBUFS):
    return can.CanOperationError(message, error_code=code)


@pytest.mark.parametrize(
    "refusal",
    [
        full_queue("Failed to transmit", errno.ENOBUFS),  # the code says it
        full_queue("No buffer space available", None),  # the text says it
    ],
    ids=["by-code", "by-text"],
)
def test_a_full_transmit_queue_is_waited_out_however_it_is_told(scripted, refusal):
    owner, node, script, _ = scripted
    script["send"] += [refusal, refusal]
    finished(
        lambda: owner.exchange(Request.of(zcan, zcan.Write(0, zcan.CanRegister.TARGET_SPEED, 0)))
    )
    assert node.bus.recv(timeout=5) is not None
    assert owner.is_open and owner.counters.timeouts == 0


def test_a_garbled_line_while_a_reply_is_awaited_is_one_frame_lost_not_the_reply(scripted):
    """An ASCII adapter's line that is no frame (python-can's slcan raises ``ValueError``)
    costs that frame, counted; the reply after it is still the reply."""
    owner, node, script, _ = scripted
    garbled = ValueError("a line that is no frame")
    ScriptedBus.ON_SEND.append(lambda timeout: script["recv"].append(garbled))  # once it went
    node.answer(ACK)
    exchange = finished(lambda: owner.exchange(speed_write()))
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert owner.counters.discarded_bytes == 1 and owner.is_open


def test_a_frame_no_reply_can_be_while_a_reply_is_awaited_does_not_end_the_wait(scripted):
    """An extended frame, counted and dropped, comes between the request and its reply."""
    owner, node, _, _ = scripted
    extended = can.Message(arbitration_id=1, data=bytes(8), is_extended_id=True)
    ScriptedBus.ON_SEND.append(lambda timeout: node.bus.send(extended))  # ahead of the reply
    node.answer(ACK)
    exchange = finished(lambda: owner.exchange(speed_write()))
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert owner.counters.discarded_bytes == 8


@pytest.mark.parametrize(
    "failure",
    [can.CanOperationError("Network is down", error_code=errno.ENETDOWN), OSError("gone")],
    ids=["can-error", "os-error"],
)
def test_a_send_that_fails_otherwise_closes_the_link_naming_why(scripted, channel, failure):
    owner, node, script, _ = scripted
    script["send"].append(failure)
    with pytest.raises(BusIOError) as lost:
        finished(lambda: owner.exchange(speed_write()))
    assert str(lost.value) == f"CAN scripted:{channel}: {failure}"
    assert lost.value.__cause__ is failure and not owner.is_open
    assert node.bus.recv(timeout=0.05) is None


def test_the_transmit_queue_gets_its_time_and_not_a_moment_more(scripted, fake_clock):
    """Each refused send waited its timeout (on the fake clock): after the first, the
    back-off's time is up to the bit, and the request fails without a second try."""
    owner, node, script, _ = scripted
    ScriptedBus.ON_SEND.append(lambda timeout: setattr(fake_clock, "t", fake_clock.t + timeout))
    for failed in (1, 2):
        script["send"].append(full_queue())
        with pytest.raises(DeviceTimeoutError, match="transmit queue full"):
            finished(lambda: owner.exchange(speed_write()))
        assert script["send"] == [] and owner.counters.timeouts == failed
    assert owner.is_open and node.bus.recv(timeout=0.05) is None


def test_the_reply_window_counts_from_the_end_of_the_frame(scripted, fake_clock):
    """The reply is there when half the frame's wire time is left of the window (the send
    took the rest, on the fake clock): it is taken."""
    owner, node, _, _ = scripted
    request = speed_write()
    wire_time = CAN_TIMING.wire_time(request.wire)
    latest = CAN_TIMING.reply_window(request)[1]

    def slow_send(timeout: float | None) -> None:
        node.send(ACK)
        fake_clock.t += wire_time + latest - wire_time / 2

    ScriptedBus.ON_SEND.append(slow_send)
    exchange = finished(lambda: owner.exchange(request))
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)


def test_a_reply_that_came_in_time_is_taken_when_the_owner_looks_late(scripted, fake_clock):
    """The reply is there before the deadline, but the owner's thread is held up past it (the
    send took the whole window, on the fake clock): one look without waiting takes it, as the
    serial owner's last look does, rather than a timeout and an unsolicited reply."""
    owner, node, _, heard = scripted
    request = speed_write()
    latest = CAN_TIMING.reply_window(request)[1]

    def held_up_send(timeout: float | None) -> None:
        node.send(ACK)
        fake_clock.t += CAN_TIMING.wire_time(request.wire) + latest + 0.001

    ScriptedBus.ON_SEND.append(held_up_send)
    exchange = finished(lambda: owner.exchange(request))
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert owner.counters.timeouts == 0 and heard == []


def test_a_receive_that_fails_closes_the_link_naming_why(scripted, channel):
    owner, _, script, _ = scripted
    failure = can.CanOperationError("adapter gone")
    script["recv"].append(failure)
    with pytest.raises(BusIOError) as lost:
        finished(lambda: owner.idle_until(now()))
    assert str(lost.value) == f"CAN scripted:{channel}: adapter gone"
    assert lost.value.__cause__ is failure and not owner.is_open


def test_a_reply_window_under_a_second_is_still_waited_for(channel, node):
    """The owner waits for the whole window, however short: a reply the node sends a moment
    after the request (from a thread of its own) is taken, not refused by a look too early."""
    owner = open_can("virtual", channel, timing=link_timing("zlac706_can", 500_000, margin_s=0.9))
    try:
        node.answer(ACK)
        exchange = finished(lambda: owner.exchange(speed_write()))
        assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    finally:
        owner.close()


def test_a_garbled_line_costs_one_frame_and_the_reply_after_it_is_taken(scripted):
    owner, node, script, heard = scripted
    request = speed_write()
    script["recv"] += [ValueError("garbled"), ValueError("garbled")]
    node.answer(ACK)
    exchange = finished(lambda: owner.exchange(request))
    assert exchange.reply == (zcan.WriteAck(1, zcan.CanRegister.TARGET_SPEED, 0),)
    assert owner.counters.discarded_bytes == 2 and heard == []


@pytest.mark.parametrize(
    "failure",
    [can.CanOperationError("already gone"), OSError("already gone")],
    ids=["can-error", "os-error"],
)
def test_an_adapter_that_fails_to_shut_down_is_closed_all_the_same(scripted, failure):
    owner, _, script, _ = scripted
    script["shutdown"].append(failure)
    owner.close()
    assert not owner.is_open


# -- CAN through an SLCAN adapter on a pty, played by the test -------------------------------


@pytest.fixture
def slcan():
    """An owner on python-can's slcan over a pty; the test writes the adapter's lines."""
    master, slave = os.openpty()
    heard: list = []
    owner = open_can("slcan", os.ttyname(slave), CAN_QUICK, heard=heard, sleep_after_open=0)
    yield owner, master, heard
    owner.close()
    os.close(master)
    os.close(slave)


def adapter_says(owner: CanBusOwner, master: int, lines: bytes) -> None:
    """Write ``lines`` as the adapter and wait until all of them are readable."""
    os.write(master, lines)
    fd = owner._bus.fileno()

    def waiting() -> int:
        return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    finished(lambda: wait_until_true(lambda: waiting() >= len(lines)))


def wait_until_true(condition: Callable[[], bool]) -> None:
    while not condition():
        select.select([], [], [], 0.001)


def test_the_bus_rate_reaches_the_adapter(slcan):
    _, master, _ = slcan
    told = bytearray()

    def opened() -> None:  # closed, set to 500 kbit/s (S6), opened again
        while b"O\r" not in told:
            select.select([master], [], [], 1)
            told.extend(os.read(master, 256))

    finished(opened)
    assert b"S6\r" in told and told.index(b"S6\r") < told.rindex(b"O\r")


def test_one_look_at_an_idle_adapter_takes_every_frame_past_its_other_lines(slcan):
    """An acknowledgement (a bare CR) is no frame: the look goes on to what follows it."""
    owner, master, heard = slcan
    finished(lambda: owner.idle_until(0.0))  # whatever the open left
    adapter_says(owner, master, b"\rt0018" + bytes.fromhex(HEARTBEAT[4:]).hex().encode() + b"\r")
    finished(lambda: owner.idle_until(0.0))  # a deadline long past: one look, no wait
    assert [event for event, _ in heard] == [zcan.HeartbeatPosition(1, 7)]


def test_one_look_takes_every_frame_one_read_brought_in(slcan):
    """Two frames that came in one chunk are read in by one read: the second waits in the
    adapter's buffer, not on its descriptor, and the same look takes it."""
    owner, master, heard = slcan
    finished(lambda: owner.idle_until(0.0))  # whatever the open left
    frames = [f"t0018{bytes.fromhex(HEARTBEAT[4:-2]).hex()}{n:02x}\r".encode() for n in (7, 9)]
    adapter_says(owner, master, b"".join(frames))
    finished(lambda: owner.idle_until(0.0))  # a deadline long past: one look, no wait
    heartbeats = [zcan.HeartbeatPosition(1, 7), zcan.HeartbeatPosition(1, 9)]
    assert [event for event, _ in heard] == heartbeats


def test_a_look_at_a_quiet_adapter_returns(slcan):
    owner, _, heard = slcan
    for _ in range(3):
        finished(lambda: owner.idle_until(0.0))
    assert heard == []


def test_a_descriptor_the_kernel_refuses_is_left_to_python_can_to_report(slcan):
    owner, _, _ = slcan
    port = owner._bus.serialPortOrig
    os.close(port.fileno())  # the adapter's descriptor, gone under python-can
    try:
        with pytest.raises(BusIOError):
            finished(lambda: owner.idle_until(0.0))
        assert not owner.is_open
    finally:
        port.fd = None  # so that nothing closes that number again, once it is reused
        port.close()


# -- serial: the owner on a pty the test plays the device on --------------------------------

LA_TIMING = link_timing("inspire_la", 921_600, margin_s=0.05, gap_s=0.001)
#: A reply window that leaves the device (a thread of the test) plenty of time.
LA_ROOMY = link_timing("inspire_la", 921_600, margin_s=0.9, gap_s=0.001)


def la_status(device_id: int, position: int = 0) -> la.StatusReply:
    return la.StatusReply(device_id, 0, position, 25, 0, 0, la.Fault(0))


STATUS_1 = Request.of(la, la.ControlCommand(1, la.ControlCode.STATUS))
NO_REPLY = Request.of(la, la.FollowCommand(1, 700, reply=False))


def queued(fd: int) -> int:
    """Bytes waiting to be read on ``fd`` (a pty end)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


class PtyDevice:
    """The far end of a pty, played by the test: what it writes, the owner reads."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.port = os.ttyname(self.slave)

    def write(self, data: bytes) -> None:
        """Write ``data`` and wait until the owner's side has all of it to read."""
        before = queued(self.slave)
        os.write(self.master, data)
        finished(lambda: wait_until_true(lambda: queued(self.slave) >= before + len(data)))

    def read(self, size: int) -> bytes:
        """``size`` bytes the owner wrote, waiting for them."""
        data = bytearray()

        def more() -> None:
            while len(data) < size:
                select.select([self.master], [], [], 1)
                data.extend(os.read(self.master, size - len(data)))

        finished(more)
        return bytes(data)

    def answer(self, *chunks: bytes, pause: float = 0.0) -> threading.Thread:
        """Once a request comes (read whole), write ``chunks``, ``pause`` seconds apart; the
        first 2 ms after the request, well after it could have left the wire (a reply that
        comes sooner is early)."""

        def respond() -> None:
            self.read(len(STATUS_1.wire))
            for chunk in chunks:
                threading.Event().wait(pause or 0.002)
                os.write(self.master, chunk)

        thread = threading.Thread(target=respond, daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):  # the test may have closed it (unplugged)
                os.close(fd)


@pytest.fixture
def device():
    device = PtyDevice()
    yield device
    device.close()


def open_serial(port: str, timing: LinkTiming = LA_TIMING) -> SerialBusOwner:
    owner = SerialBusOwner(port, la, timing, BusCounters(0.0))
    owner.open()
    return owner


@pytest.fixture
def serial_fake_clock(monkeypatch) -> FakeClock:
    """The serial owner's clock and its precise wait on one fake clock (``select`` still
    waits in real time: with the clock stopped, a reply window lasts its length for real)."""
    clock = FakeClock()
    monkeypatch.setattr(serial_owner_module, "now", clock)
    monkeypatch.setattr(serial_owner_module, "sleep_until", clock.sleep_until)
    return clock


def test_a_silent_device_times_out_by_id_each_time_and_the_link_stays(device):
    owner = open_serial(device.port, link_timing("inspire_la", 921_600, margin_s=0.01))
    try:
        for _ in range(2):
            with pytest.raises(DeviceTimeoutError) as timeout:
                finished(lambda: owner.exchange(STATUS_1))
            assert str(timeout.value) == f"no reply from id 1 on {device.port}"
            assert timeout.value.device_id == 1
        counters = owner.counters
        assert (counters.timeouts, counters.frames_out) == (2, 2)
        assert counters.bytes_out == 2 * len(STATUS_1.wire) and owner.is_open
    finally:
        owner.close()


def test_a_silent_device_of_a_link_without_ids_is_told_as_the_device(device):
    """RS232's frames carry no id: its timeout said "no reply from id None" (a wire audit)."""
    owner = open_serial(device.port, link_timing("zlac706_rs232", 115_200, margin_s=0.01))
    try:
        with pytest.raises(DeviceTimeoutError) as timeout:
            finished(lambda: owner.exchange(Request.of(zrs232, zrs232.MonitorRequest())))
        assert str(timeout.value) == f"no reply from the device on {device.port}"
    finally:
        owner.close()


def test_the_answer_is_found_among_noise_and_everything_is_counted(device):
    """Noise, a frame with a bad checksum and another actuator's status come first (and a
    pause, the reply window still open); then the answer. Twice, for the running totals."""
    owner = open_serial(device.port, LA_ROOMY)
    answer = la.encode(la_status(1, 123))
    bad = bytearray(la.encode(la_status(1)))
    bad[-1] ^= 0xFF
    before_answer = [b"\x13\x37\x00", bytes(bad), la.encode(la_status(2))]
    try:
        for _ in range(2):
            device.answer(*before_answer, answer, pause=0.02)
            before = now()
            exchange = finished(lambda: owner.exchange(STATUS_1))
            assert exchange.request is STATUS_1 and exchange.reply == (la_status(1, 123),)
            assert 0 < exchange.write_s <= exchange.start - before
            assert exchange.start < exchange.end <= now()
        counters = owner.counters
        assert counters.bytes_in == 2 * (sum(map(len, before_answer)) + len(answer))
        # The bad frame's first byte is its mismatch; the rest is discarded, as the noise is.
        assert counters.discarded_bytes == 2 * (3 + len(bad) - 1)
        assert counters.checksum_errors == 2
        assert (counters.frames_in, counters.late_replies, counters.early_replies) == (4, 2, 0)
        assert counters.timeouts == 0
    finally:
        owner.close()


def test_a_frame_without_a_reply_holds_the_serial_line_for_its_wire_time(device):
    owner = open_serial(device.port)
    try:
        before = now()
        exchange = finished(lambda: owner.exchange(NO_REPLY))
        after = now()
        assert exchange.request is NO_REPLY and before <= exchange.start <= after
        assert exchange.reply == ()  # no events, but a tuple of them, as with an answer
        # its wire time from when it had left the port's driver: a pty's, at the first look
        wire = LA_TIMING.wire_time(NO_REPLY.wire)
        assert exchange.start + wire <= exchange.end <= after + wire
        assert 0 < exchange.write_s <= exchange.start - before
        assert device.read(len(NO_REPLY.wire)) == NO_REPLY.wire
        assert (owner.counters.frames_out, owner.counters.bytes_out) == (1, len(NO_REPLY.wire))
    finally:
        owner.close()


def test_answers_before_the_request_could_have_left_the_wire_are_early_and_said(
    device, serial_fake_clock
):
    """The clock stands still: every answer comes at the moment of the write, before the
    frame could have left the wire, as from an emulator without wire timing."""
    owner = open_serial(device.port)
    try:
        device.answer(la.encode(la_status(1)), la.encode(la_status(1)))
        with pytest.raises(DeviceTimeoutError) as timeout:
            finished(lambda: owner.exchange(STATUS_1))
        assert str(timeout.value) == (
            f"no reply from id 1 on {device.port}; 2 came before the request could have left "
            "the wire at 921600 baud: is the baud rate right, or is this an emulator without "
            "wire timing?"
        )
        assert (owner.counters.early_replies, owner.counters.frames_in) == (2, 2)
    finally:
        owner.close()


def test_an_answer_is_early_until_the_frame_and_the_shortest_reply_time_have_passed(
    device, serial_fake_clock
):
    """One answer half the shortest reply time too soon (early), one exactly on time
    (taken): the earliest moment counts from when the write was issued."""
    timing = link_timing("inspire_la", 921_600, margin_s=2.0, gap_s=0.001)
    owner = open_serial(device.port, timing)
    clock = serial_fake_clock
    issued = clock()
    wire_time = timing.wire_time(STATUS_1.wire)
    shortest = timing.reply_window(STATUS_1)[0]

    def respond() -> None:
        device.read(len(STATUS_1.wire))
        clock.t = issued + wire_time + shortest / 2
        os.write(device.master, la.encode(la_status(1, 1)))
        wait_until_true(lambda: owner.counters.early_replies == 1)
        clock.t = issued + wire_time + shortest
        os.write(device.master, la.encode(la_status(1, 2)))

    threading.Thread(target=respond, daemon=True).start()
    try:
        exchange = finished(lambda: owner.exchange(STATUS_1))
        assert exchange.reply == (la_status(1, 2),) and owner.counters.early_replies == 1
    finally:
        owner.close()


class HeldUpClock(FakeClock):
    """A clock that plays a bus thread held up right after its write: the first reading
    once the owner has counted its frame out writes ``late`` as the device, waits until it
    can be read, and is a minute past, as is every reading after it."""

    def __init__(self, device: PtyDevice, late: bytes) -> None:
        super().__init__()
        self.device, self.late = device, late
        self.owner: SerialBusOwner | None = None
        self.held = False

    def __call__(self) -> float:
        if not self.held and self.owner is not None and self.owner.counters.frames_out:
            self.held = True
            self.device.write(self.late)
        return self.t + 60.0 if self.held else self.t


@pytest.mark.parametrize("late", ["answer", "noise"])
def test_past_the_deadline_one_last_look_still_takes_an_answer_that_came_in_time(
    device, monkeypatch, late
):
    answer = la.encode(la_status(1, 9))
    clock = HeldUpClock(device, answer if late == "answer" else b"\x13\x37")
    monkeypatch.setattr(serial_owner_module, "now", clock)
    owner = clock.owner = open_serial(device.port)
    try:
        if late == "answer":
            exchange = finished(lambda: owner.exchange(STATUS_1))
            assert exchange.reply == (la_status(1, 9),)
        else:
            with pytest.raises(DeviceTimeoutError):
                finished(lambda: owner.exchange(STATUS_1))
            assert owner.counters.discarded_bytes == 2 and owner.counters.timeouts == 1
    finally:
        owner.close()


class WindowClock(FakeClock):
    """A clock stopped at the exchange's start until the owner has counted its frame out;
    then ``left`` seconds before the reply deadline: noise comes at that moment, and once
    the owner has read it, the answer."""

    def __init__(self, device: PtyDevice, timing: LinkTiming, request: Request, left: float):
        super().__init__()
        self.device, self.owner = device, None
        wire_time = timing.wire_time(request.wire)
        deadline = self.t + wire_time + timing.reply_window(request)[1]  # as the owner adds
        self.then = deadline - left
        self.stage = 0

    def __call__(self) -> float:
        if self.stage == 0 and self.owner is not None and self.owner.counters.frames_out:
            self.stage = 1
            self.device.write(b"\x13\x37")
        elif self.stage == 1 and queued(self.device.slave) == 0:
            self.stage = 2
            self.device.write(la.encode(la_status(1)))
        return self.then if self.stage else self.t


@pytest.mark.parametrize("left", ["half the wire time", "nothing"])
def test_the_reply_window_counts_from_the_frames_end_and_its_end_is_the_last_look(
    device, monkeypatch, left
):
    """Noise, then the answer, at one moment of the window: with half the frame's wire time
    left, the answer is taken; at the deadline itself, the look that found the noise was the
    last, and the exchange times out."""
    wire_time = LA_TIMING.wire_time(STATUS_1.wire)
    clock = WindowClock(device, LA_TIMING, STATUS_1, wire_time / 2 if left != "nothing" else 0.0)
    monkeypatch.setattr(serial_owner_module, "now", clock)
    owner = clock.owner = open_serial(device.port)
    try:
        if left == "nothing":
            with pytest.raises(DeviceTimeoutError):
                finished(lambda: owner.exchange(STATUS_1))
        else:
            assert finished(lambda: owner.exchange(STATUS_1)).reply == (la_status(1),)
        assert clock.stage == 2
    finally:
        owner.close()


def test_stale_input_is_flushed_and_counted_before_each_request(device):
    """Noise, two other actuators' replies and the start of a frame, before each of two
    requests: all of it dropped, and counted."""
    owner = open_serial(device.port, LA_ROOMY)
    partial = la.encode(la_status(1))[:5]
    stale = b"\x13\x37\x00" + la.encode(la_status(2)) + la.encode(la_status(3)) + partial
    try:
        for _ in range(2):
            device.write(stale)
            device.answer(la.encode(la_status(1)))
            assert finished(lambda: owner.exchange(STATUS_1)).reply == (la_status(1),)
        assert owner.counters.late_replies == 2 * 2
        assert owner.counters.discarded_bytes == 2 * (3 + len(partial))
    finally:
        owner.close()


def test_a_quiet_line_is_written_at_once(device, serial_fake_clock):
    owner = open_serial(device.port)
    try:
        start = serial_fake_clock()
        exchange = finished(lambda: owner.exchange(NO_REPLY))
        assert exchange.start == start
        assert exchange.last_byte_before == -math.inf  # nothing read yet: no gap to count
    finally:
        owner.close()


def test_a_timed_serial_send_goes_at_its_moment(device, serial_fake_clock):
    owner = open_serial(device.port)
    try:
        at = serial_fake_clock() + 0.05
        assert finished(lambda: owner.exchange(NO_REPLY, at=at)).start == at
    finally:
        owner.close()


def test_a_line_that_keeps_talking_is_written_when_the_quiet_wait_gives_up(
    device, serial_fake_clock, monkeypatch
):
    """Noise before the request and during every wait for the gap (a gap as long as the
    whole quiet wait): the write goes at the end of the quiet wait, not a gap later."""
    timing = link_timing("inspire_la", 921_600, margin_s=0.05, gap_s=QUIET_WAIT_MAX_S)
    owner = open_serial(device.port, timing)
    clock = serial_fake_clock
    waits = []

    def noisy_wait(deadline: float, **_: object) -> float:
        waits.append(deadline)
        if len(waits) > 10:
            raise AssertionError("the quiet wait does not give up")
        device.write(b"\x00")
        return clock.sleep_until(deadline)

    monkeypatch.setattr(serial_owner_module, "sleep_until", noisy_wait)
    try:
        start = clock()
        device.write(b"\x00")
        exchange = finished(lambda: owner.exchange(NO_REPLY))
        assert exchange.start == start + QUIET_WAIT_MAX_S and len(waits) == 1
        assert owner.counters.discarded_bytes == 2
    finally:
        owner.close()


def fill(owner: SerialBusOwner) -> None:
    """Write through the owner's descriptor until the pty takes no more, even after a
    moment (the kernel moves what it has buffered along in its own time)."""

    def until_full() -> None:
        fd = owner._serial.fileno()
        while True:
            try:
                while True:
                    os.write(fd, b"\x00" * 256)
            except BlockingIOError:
                pass
            threading.Event().wait(0.02)
            try:
                os.write(fd, b"\x00")
            except BlockingIOError:
                return

    finished(until_full)


def test_a_line_that_takes_nothing_fails_the_write_after_its_timeout(device):
    owner = open_serial(device.port)
    try:
        fill(owner)
        with pytest.raises(BusIOError) as lost:
            finished(lambda: owner.exchange(NO_REPLY))
        assert str(lost.value) == (
            f"{device.port}: write timeout: the port took no more bytes for 0.5 s")
        assert not owner.is_open
    finally:
        owner.close()


def test_a_frame_the_kernel_takes_none_of_at_first_goes_out_whole_later(device, monkeypatch):
    monkeypatch.setattr(serial_owner_module, "WRITE_TIMEOUT_S", 10.0)  # room for the reader
    owner = open_serial(device.port)
    drained = bytearray()
    try:
        fill(owner)
        filled = queued(device.master)

        def drain_later() -> None:
            threading.Event().wait(0.3)  # the owner's first write has found the pty full
            while not drained.endswith(NO_REPLY.wire):
                select.select([device.master], [], [], 1)
                drained.extend(os.read(device.master, 65536))

        reader = threading.Thread(target=drain_later, daemon=True)
        reader.start()
        finished(lambda: owner.exchange(NO_REPLY))
        reader.join(10)
        assert bytes(drained[-len(NO_REPLY.wire) :]) == NO_REPLY.wire
        assert len(drained) >= filled + len(NO_REPLY.wire)
    finally:
        owner.close()


def test_a_port_opens_at_the_bus_rate_and_for_one_owner_only(device):
    owner = open_serial(device.port)
    try:
        assert termios.tcgetattr(device.slave)[4] == termios.B921600
        second = SerialBusOwner(device.port, la, LA_TIMING, BusCounters(0.0))
        with pytest.raises(BusUnavailableError) as refused:
            second.open()
        assert str(refused.value) == describe_open_error(device.port, refused.value.__cause__)
        assert not second.is_open
    finally:
        owner.close()


def test_a_port_that_does_not_exist_is_unavailable_with_the_story(tmp_path):
    port = str(tmp_path / "ttyUSB9")
    owner = SerialBusOwner(port, la, LA_TIMING, BusCounters(0.0))
    with pytest.raises(BusUnavailableError) as refused:
        owner.open()
    assert str(refused.value) == describe_open_error(port, refused.value.__cause__)
    assert port in str(refused.value)


def test_a_port_not_open_is_named(device):
    owner = SerialBusOwner(device.port, la, LA_TIMING, BusCounters(0.0))
    with pytest.raises(BusIOError) as closed:
        owner.exchange(STATUS_1)
    assert str(closed.value) == f"{device.port} is not open"


def test_an_adapter_gone_while_awaited_closes_the_link_naming_why(device):
    owner = open_serial(device.port, LA_ROOMY)
    try:

        def unplug() -> None:
            device.read(len(STATUS_1.wire))
            os.close(device.master)

        threading.Thread(target=unplug, daemon=True).start()
        with pytest.raises(BusIOError) as lost:
            finished(lambda: owner.exchange(STATUS_1))
        assert str(lost.value) == (
            f"{device.port}: the port reports data but returns none (unplugged?)"
        )
        assert not owner.is_open
    finally:
        owner.close()


def test_a_port_whose_descriptor_is_gone_is_closed_all_the_same(device):
    owner = open_serial(device.port)
    port = owner._serial
    os.close(port.fileno())  # gone under pyserial: its own close fails
    try:
        owner.close()
        assert not owner.is_open
    finally:
        port.fd = None  # so that nothing closes that number again, once it is reused
        port.close()


# -- what travels between scheduler and owner ------------------------------------------------


def test_a_request_carries_its_frame_and_is_sent_once_unless_it_may_be_retried():
    frame = la.ControlCommand(1, la.ControlCode.STATUS)
    request = Request.of(la, frame)
    assert (request.frame, request.wire) == (frame, la.encode(frame))
    assert request.expected == la.expected_reply(frame) and request.idempotent is False
    assert Request.of(la, frame, idempotent=True).idempotent is True


def test_link_timing_of_a_frame_without_reply_is_its_wire_time():
    assert LA_TIMING.reply_window(NO_REPLY) == (0.0, 0.0)
    assert LA_TIMING.worst_case(NO_REPLY) == LA_TIMING.wire_time(NO_REPLY.wire)


def test_link_timing_of_a_reply_adds_the_reply_window_to_the_frame():
    from busgate.codecs.framing import ExpectedReply
    from busgate.codecs.timing import can_time

    expected = ExpectedReply(1, 8, (zcan.WriteAck,), frames=3)
    assert CAN_QUICK.reply_time(expected) == 3 * can_time(8, 500_000)
    request = speed_write()
    timing = zcan.TIMING
    latest = timing.reply_max_s + CAN_QUICK.reply_time(request.expected) + 0.01
    assert CAN_QUICK.reply_window(request) == (timing.reply_min_s, latest)
    assert CAN_QUICK.worst_case(request) == CAN_QUICK.wire_time(request.wire) + latest


# -- the tap: what the flight recorder is given -------------------------------------------


def test_the_tap_is_given_every_frame_written_and_read_on_a_serial_line(device):
    """Stale input flushed before the request, the request, and its reply, each with its
    direction and the time it was read or written; CAN's identifier ``None``."""
    owner = open_serial(device.port, LA_ROOMY)
    tapped: list[tuple] = []
    owner.tap = tapped.append
    reply = la.encode(la_status(1))
    try:
        device.write(b"\x13\x37")
        device.answer(reply)
        before = now()
        exchange = finished(lambda: owner.exchange(STATUS_1))
        assert [(way, data, ident) for _, way, data, ident in tapped] == [
            (RX, b"\x13\x37", None),
            (TX, STATUS_1.wire, None),
            (RX, reply, None),
        ]
        assert before <= tapped[0][0] <= tapped[1][0] == exchange.start  # read, then flushed
        assert exchange.start < tapped[2][0] <= exchange.end
    finally:
        owner.close()


def test_the_tap_is_given_every_can_frame_but_those_no_reply_can_be(channel, node):
    """The request, its reply and a heartbeat, with their identifiers; an extended frame and
    a remote frame are counted as discarded and never tapped (a flight record of frames the
    gateway cannot read would show them as node 0's)."""
    heard: list = []
    owner = open_can("virtual", channel, heard=heard)
    tapped: list[tuple] = []
    owner.tap = tapped.append
    try:
        node.bus.send(can.Message(arbitration_id=1, data=bytes(8), is_extended_id=True))
        node.bus.send(
            can.Message(arbitration_id=1, is_remote_frame=True, dlc=8, is_extended_id=False)
        )
        node.send("7FF#00")  # the last standard identifier: a frame, though no node's
        node.send(HEARTBEAT)
        finished(lambda: wait_heard(owner, heard, 1))
        node.answer(ACK)
        request = speed_write()
        exchange = finished(lambda: owner.exchange(request))
        assert [(way, data, ident) for _, way, data, ident in tapped] == [
            (RX, b"\x00", 0x7FF),
            (RX, CanFrame.parse(HEARTBEAT).data, 1),
            (TX, request.wire.data, 1),
            (RX, CanFrame.parse(ACK).data, 1),
        ]
        assert exchange.start <= tapped[2][0] <= tapped[3][0] <= exchange.end
    finally:
        owner.close()
