"""The owner of one CAN interface, through python-can (socketcan, slcan, pcan, virtual …): a
``BusOwner``.

Rules of this file:

1. Only the bus thread uses the ``can.Bus``; ``interface``, ``channel``, ``bitrate`` and any
   further options of the config pass through to python-can untouched.
2. Every exception from python-can is caught and classified here. A ``ValueError`` from
   receiving is a garbled adapter line (slcan over a full tty buffer): one frame is lost,
   the link is fine. "No buffer space" (the
   kernel's transmit queue is full) is back-pressure: wait briefly and retry, and if the queue
   stays full the request fails like a timeout. A lost adapter or bus-off is a link failure:
   the bus is closed and ``BusIOError`` raised so the runner reconnects.
3. Frames nobody asked for (heartbeats, alarm reports) are decoded and handed to
   ``on_unsolicited`` with their arrival time (rule 7), both while waiting for a reply and
   while idle (every ``idle_batch_s``). Taking what has already arrived never waits: a look is a
   ``recv(timeout=0)`` where that never waits (SocketCAN, our SLCAN reads, a bus with no
   descriptor such as ``virtual``); any other adapter with a descriptor is asked through it
   first, since a serial one (python-can's own slcan, ``serial``, ``seeedstudio`` …) blocks a
   ``recv(timeout=0)`` for its serial timeout when nothing is there, which would make a timed
   send late (asking SocketCAN's descriptor first would cost a ``select`` a frame). A look
   takes at most ``LOOK_FRAMES_MAX`` frames, and a wait for a reply as many past its
   deadline: a bus flooded past what a CAN bus carries is not read for ever, an e-stop's
   turn comes (the rest waits in the adapter's queue, which drops what it cannot hold).
4. Only this module converts between ``CanFrame`` and ``can.Message``, or SocketCAN's bytes.
5. An SLCAN adapter is python-can's ``slcan`` interface with its reads replaced
   (``slcan.SlcanBus``: a chunk a read, not a byte), made as ``can.Bus`` makes python-can's
   (the same arguments, python-can's configuration read the same way).
6. On SocketCAN, frames are read from python-can's socket here, one ``recvmsg`` a frame and
   no ``can.Message``: python-can's ``recv`` asks ``select`` first and builds a message, a
   third of a heartbeat frame's cost, none of which the owner uses. The socket is
   python-can's, opened and set up by it (error frames, FD, the kernel's receive time), and it
   still sends; a bus given ``can_filters`` is read through python-can, which applies them.
   Every frame, however read, is one ``(identifier, data, arrival)``: the identifier with
   SocketCAN's flags (extended, remote, error), the data as the frame carries it.
7. A frame is dated by its arrival: on SocketCAN, the kernel's receive time that python-can
   asks for (``SO_TIMESTAMPNS``, the wall clock) brought to the bus clock; else, or when that
   time cannot be right (none, ahead of now, or older than ``ARRIVAL_AGE_MAX_S``: the wall
   clock was set meanwhile), the moment it is taken; and never before the frame before it,
   so that a device's times only go forward. A look while idle comes every
   ``idle_batch_s``: dated by the look, a heartbeat's state would carry a time up to that much
   after the heartbeat, and two states' times, which clients take apart for a velocity, would
   jitter by as much. An exchange ends when its reply's last frame is dated: a heartbeat
   taken after the reply came after it, and is dated so.
"""

from __future__ import annotations

import contextlib
import errno
import math
import select
import socket
import struct
import time
from collections.abc import Callable, Mapping
from functools import partial
from types import ModuleType
from typing import Any, ClassVar

import can
from can.interfaces.socketcan.constants import SO_TIMESTAMPNS

from busgate.codecs.can_frame import MAX_STANDARD_ID, CanFrame
from busgate.codecs.framing import Discarded
from busgate.errors import BusIOError, BusUnavailableError, DeviceTimeoutError
from busgate.gateway.bus.clock import now, sleep_until
from busgate.gateway.bus.owner import RX, TX, BusOwner
from busgate.gateway.bus.request import Exchange, LinkTiming, Request
from busgate.gateway.bus.slcan import SlcanBus
from busgate.gateway.bus.stats import BusCounters

#: How long a full transmit queue may hold a request back before it counts as failed.
TX_BACKPRESSURE_S = 0.05
#: The last stretch before a timed send is waited out precisely, not in ``recv``.
PRECISE_WAIT_S = 0.001
#: The error-frame flag (in the identifier of an error frame) that says the controller is bus-off.
CAN_ERR_BUSOFF = 0x40
#: SocketCAN's flags in a frame's identifier (linux/can.h): extended, remote, error frame.
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
#: SocketCAN's frame header (``struct can_frame`` and ``canfd_frame``): the identifier with its
#: flags, the data's length, three bytes more; the data follows.
SOCKETCAN_HEADER = struct.Struct("=IB3x")
#: The largest frame a SocketCAN socket gives (a CAN FD frame).
CANFD_MTU = 72
#: Each frame's receive time, as python-can's SocketCAN bus asks for it (``SO_TIMESTAMPNS``):
#: a ``struct timespec`` of the wall clock.
TIMESPEC = struct.Struct("@ll")
RECEIVE_TIME_SPACE = socket.CMSG_SPACE(TIMESPEC.size)
#: A frame's receive time older than this when it is taken is not believed (rule 7): frames do
#: not wait that long in the socket while the bus thread runs, so the wall clock was set.
ARRIVAL_AGE_MAX_S = 1.0
#: A frame taken: its identifier with SocketCAN's flags, its data, and its arrival on the bus
#: clock (``None``: dated when taken; rule 7).
TakenFrame = tuple[int, bytes, float | None]
#: Takes the next frame, waiting up to its argument (s); ``None`` when none came (``frames_of``).
TakeFrame = Callable[[float], TakenFrame | None]
#: The most frames one look takes (rule 3): a 1 Mbit/s bus carries some 70 in an idle
#: batch's 8 ms.
LOOK_FRAMES_MAX = 256
#: The interfaces with a descriptor whose ``recv(timeout=0)`` never waits (rule 3; slcan is
#: ours, ``SlcanBus``).
LOOK_NEVER_WAITS = frozenset({"socketcan", "slcan"})


class CanBusOwner(BusOwner):
    """Runs exchanges on one CAN interface and routes unsolicited frames."""

    #: While idle, frames are taken in batches this far apart: heartbeats are telemetry, so a
    #: few milliseconds of delay cost nothing, while waking for each frame of a burst costs a
    #: wake-up apiece. Shorter than the usual 10 ms heartbeat interval, so that each heartbeat
    #: still makes its own telemetry.
    idle_batch_s: ClassVar[float] = 0.008

    def __init__(
        self,
        interface: str,
        channel: str,
        options: Mapping[str, Any],
        codec: ModuleType,
        timing: LinkTiming,
        counters: BusCounters,
        on_unsolicited: Callable[[object, float], None],
    ) -> None:
        self.interface, self.channel, self.options = interface, channel, dict(options)
        self.port = f"{interface}:{channel}"
        self.codec = codec
        self.timing = timing
        self.counters = counters
        self.on_unsolicited = on_unsolicited
        self._bus: can.BusABC | None = None
        #: The descriptor asked before each look (rule 3); ``None``: a look never waits.
        self._fd: int | None = None
        #: How frames are taken while open (``frames_of``; rule 6).
        self._take: TakeFrame | None = None
        self._decoder = codec.ReplyDecoder()
        #: The time given to the last frame dated (rule 7): none is dated before it.
        self._dated = -math.inf

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def open(self) -> None:
        try:
            self._bus = self._make_bus()
        except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
            # TypeError: an option the interface's class does not take
            raise BusUnavailableError(f"cannot open CAN {self.port}: {exc}") from exc
        self._take = frames_of(self.interface, self._bus)
        if self.interface in LOOK_NEVER_WAITS:
            return
        try:
            self._fd = self._bus.fileno()
        except (NotImplementedError, can.CanError):
            self._fd = None  # e.g. the virtual bus: its recv(timeout=0) does not wait

    def _make_bus(self) -> can.BusABC:
        arguments = dict(  # an option naming one of these again: TypeError, as can.Bus raises
            interface=self.interface, channel=self.channel, bitrate=self.timing.rate, **self.options
        )
        if self.interface != "slcan":
            return can.Bus(**arguments)
        # What can.Bus does, with our class for python-can's (rule 5).
        arguments = can.util.load_config(config=arguments)
        del arguments["interface"]
        return SlcanBus(**arguments)

    def close(self) -> None:
        bus, self._bus, self._fd, self._take = self._bus, None, None, None
        if bus is not None:
            with contextlib.suppress(can.CanError, OSError):  # the adapter may be gone already
                bus.shutdown()

    def exchange(self, request: Request, *, at: float | None = None) -> Exchange:
        bus = self._require_open()
        if at is None:
            self.idle_until(now())
        else:  # the adapter's receive timeout is coarse: take in frames, then wait precisely
            if at - now() > PRECISE_WAIT_S:  # not later: a look at the frames takes time
                self.idle_until(at - PRECISE_WAIT_S)
            sleep_until(at)
        start = now()
        assert isinstance(request.wire, CanFrame)  # a CAN codec's frames
        self._send(bus, request.wire)
        wire_time = self.timing.wire_time(request.wire)
        answer: tuple[object, ...] | None = ()
        end = start + wire_time
        if request.expected is not None:
            _, latest = self.timing.reply_window(request)
            answer = self._receive_until(start + wire_time + latest, request.expected)
            if answer is None:
                self.counters.timeouts += 1
                source = request.expected.source_id
                raise DeviceTimeoutError(
                    f"no reply from node {source} on {self.port}", device_id=source
                )
            # When the reply's last frame came (rule 7); one that came before the request
            # went was a late answer to an earlier one, taken as this one's.
            end = max(self._dated, start)
        return Exchange(request, start, end, answer or ())

    def take_unsolicited(self) -> None:
        self._require_open()
        self._receive_until(now(), None)  # a deadline now: one look

    def _require_open(self) -> can.BusABC:
        if self._bus is None:
            raise BusIOError(f"CAN {self.port} is not open")
        return self._bus

    def _send(self, bus: can.BusABC, wire: CanFrame) -> None:
        message = can.Message(
            arbitration_id=wire.arbitration_id, data=wire.data, is_extended_id=False
        )
        give_up = now() + TX_BACKPRESSURE_S
        while True:
            try:
                bus.send(message, timeout=TX_BACKPRESSURE_S)
                break
            except can.CanError as exc:
                if not _is_backpressure(exc):
                    self._fail(exc)
                if now() >= give_up:
                    self.counters.timeouts += 1
                    raise DeviceTimeoutError(f"CAN {self.port}: transmit queue full") from exc
                time.sleep(0.001)
            except OSError as exc:
                self._fail(exc)
        if self.tap is not None:
            self.tap((now(), TX, wire.data, wire.arbitration_id))
        self.counters.frames_out += 1
        self.counters.bytes_out += len(wire.data)

    def _receive_until(self, deadline: float, expected) -> tuple[object, ...] | None:
        """Receive until ``expected`` is complete or ``deadline``, then take what is already
        there without waiting (as the serial owner does: a reply that came in time is the
        reply, even when this thread was held up past the deadline); ``None`` if incomplete.
        A deadline that has passed is that one look: what came unasked, taken while idle."""
        answer: list[object] = []
        take, unsolicited = self._take, self.on_unsolicited  # once: this loop runs per frame
        assert take is not None  # only while open
        looked = 0  # frames taken past the deadline (rule 3)
        while True:
            remaining = deadline - now()
            waiting = remaining > 0
            if not waiting:
                if looked >= LOOK_FRAMES_MAX or not self._input_waiting():
                    return None
                looked += 1
            try:
                frame = take(remaining if waiting else 0)
            except (can.CanError, OSError) as exc:
                self._fail(exc)
            except ValueError:  # a garbled line from an ASCII (slcan) adapter: one frame lost
                self.counters.discarded_bytes += 1
                continue
            if frame is None:
                if waiting or self._fd is not None or self._has_line():
                    continue  # the wait ended (then one look more), or a line that was no frame
                return None
            can_id, data, arrival = frame
            when = self._date(arrival)
            event = self._decode(can_id, data, when)
            if event is None:
                continue
            if expected is not None and expected.matches(event):
                answer.append(event)
                if len(answer) >= expected.frames:
                    return tuple(answer)
            else:
                unsolicited(event, when)

    def _date(self, arrival: float | None) -> float:
        """A frame's time (rule 7): its arrival, else now, and never before the frame before."""
        dated = now() if arrival is None else arrival
        if dated < self._dated:
            dated = self._dated
        self._dated = dated
        return dated

    def _input_waiting(self) -> bool:
        """Whether the adapter may have a frame for us (always, when a look never waits)."""
        if self._fd is None:
            return True
        try:
            readable, _, _ = select.select([self._fd], [], [], 0)
        except (OSError, ValueError):
            return True  # let recv report what is wrong with the adapter
        return bool(readable)

    def _has_line(self) -> bool:
        """Whether an SLCAN adapter's lines read in hold another (one that was no frame, an
        acknowledgement, came first and made its look find nothing)."""
        return isinstance(self._bus, SlcanBus) and self._bus.has_line

    def _decode(self, can_id: int, data: bytes, when: float) -> object | None:
        """The event a frame that came ``when`` makes (a CAN frame makes one), ``None`` when it
        makes none (an error frame, a frame no reply can be, bytes the codec discarded:
        counted)."""
        counters = self.counters
        if can_id & CAN_ERR_FLAG:
            if can_id & CAN_ERR_BUSOFF:
                self._fail(can.CanOperationError("controller is bus-off"))
            return None
        counters.frames_in += 1
        counters.bytes_in += len(data)
        # extended or remote (a flag above the identifier's bits), or FD: no reply is one
        if can_id > MAX_STANDARD_ID or len(data) > 8:
            counters.discarded_bytes += len(data)
            return None
        if self.tap is not None:
            self.tap((when, RX, data, can_id))
        event = self._decoder.decode(CanFrame(can_id, data))
        if isinstance(event, Discarded):
            counters.discarded_bytes += len(event.data)
            return None
        return event

    def _fail(self, exc: BaseException) -> None:
        self.close()
        raise BusIOError(f"CAN {self.port}: {exc}") from exc


def frames_of(interface: str, bus: can.BusABC) -> TakeFrame:
    """How frames are taken from ``bus``, each as SocketCAN's ``(identifier, data)`` (rule
    6): read from python-can's SocketCAN socket, unless the bus's class has none or it was
    given ``can_filters`` (python-can filters in software where the kernel refuses them);
    else through python-can's ``recv``."""
    sock = getattr(bus, "socket", None)
    if interface == "socketcan" and isinstance(sock, socket.socket) and not bus.filters:
        return partial(_take_from_socket, sock)
    return partial(_take_from_bus, bus)


def _take_from_socket(sock: socket.socket, timeout: float) -> TakenFrame | None:
    """The next frame on SocketCAN's socket, waiting up to ``timeout``, with its arrival."""
    if timeout > 0 and not select.select([sock], [], [], timeout)[0]:
        return None
    try:
        frame, receive_time, _, _ = sock.recvmsg(CANFD_MTU, RECEIVE_TIME_SPACE, socket.MSG_DONTWAIT)
    except BlockingIOError:
        return None
    if not frame:  # SocketCAN never gives an empty frame: the socket's far end is gone
        raise can.CanOperationError("the interface's socket was closed")
    can_id, length = SOCKETCAN_HEADER.unpack_from(frame)
    if can_id & CAN_RTR_FLAG:  # its length asks for data; it carries none
        data = b""
    else:
        data = frame[SOCKETCAN_HEADER.size : SOCKETCAN_HEADER.size + length]
    return can_id, data, _arrival(receive_time)


def _arrival(receive_time: list[tuple[int, int, bytes]]) -> float | None:
    """The kernel's receive time of a frame (``recvmsg``'s ancillary data) on the bus clock;
    ``None`` when there is none or it cannot be right (rule 7)."""
    for level, kind, timespec in receive_time:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(timespec) >= TIMESPEC.size:
            seconds, nanoseconds = TIMESPEC.unpack_from(timespec)
            age = time.time() - seconds - nanoseconds * 1e-9
            if 0.0 <= age <= ARRIVAL_AGE_MAX_S:
                return now() - age
    return None


def _take_from_bus(bus: can.BusABC, timeout: float) -> TakenFrame | None:
    """The next frame through python-can's ``recv``, waiting up to ``timeout``, dated when
    taken (``Message.timestamp``'s clock is the interface's own)."""
    message = bus.recv(timeout=timeout)
    if message is None:
        return None
    can_id = message.arbitration_id
    if message.is_extended_id:
        can_id |= CAN_EFF_FLAG
    if message.is_remote_frame:
        can_id |= CAN_RTR_FLAG
    if message.is_error_frame:
        can_id |= CAN_ERR_FLAG
    return can_id, bytes(message.data), None


def _is_backpressure(exc: can.CanError) -> bool:
    """True for "no buffer space": the transmit queue is full, the link is fine."""
    return getattr(exc, "error_code", None) == errno.ENOBUFS or "buffer space" in str(exc)
