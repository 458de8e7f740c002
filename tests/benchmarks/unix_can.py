"""CAN frames between processes on a host without SocketCAN, for benchmarks (and for
``tests/test_socketcan_owner.py``, which writes SocketCAN's bytes to its far end).

This virtual machine has no ``vcan`` module, and python-can's ``virtual`` bus does not cross
processes, so a benchmark of heartbeats either ran its simulators in the daemon's process
(where their turns on the interpreter are charged to the daemon's threads) or behind SLCAN
adapters (where python-can's parsing of each ASCII line is). This bus stands where SocketCAN
would: one ``SOCK_SEQPACKET`` connection per bus, each datagram one frame in SocketCAN's own
layout (``struct can_frame``: identifier, length, three bytes of padding, eight of data),
read as python-can's ``socketcan`` reads one (a ``select`` on the descriptor, one read a
frame, a ``can.Message`` made of it). A simulator's process listens on a name in Linux's
abstract socket namespace (no file, nothing left behind); the daemon connects to it.
``register`` puts it where python-can finds SocketCAN's class, in the benchmark's process
only: the daemon there takes a bus of ``interface = "socketcan"`` as it takes SocketCAN.
"""

from __future__ import annotations

import select
import socket
import struct
import time

import can
from can.interfaces.socketcan.constants import SO_TIMESTAMPNS

#: The interface whose class this bus stands in for (``register``).
INTERFACE = "socketcan"
#: SocketCAN's ``struct can_frame``.
FRAME = struct.Struct("=IB3x8s")
#: SocketCAN's flag for an extended (29-bit) identifier.
EXTENDED = 0x80000000
#: How long a listening end waits for the other (a benchmark that died never connects).
ACCEPT_TIMEOUT_S = 60.0


class UnixCanBus(can.BusABC):
    """One end of the bus named ``channel``: the other end's ``connect``, or the end that a
    ``listening`` socket accepted."""

    def __init__(self, channel: str, *, accepted: socket.socket | None = None, **kwargs) -> None:
        if accepted is not None:
            self.socket = accepted
        else:
            self.socket = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                self.socket.connect(_address(channel))
            except OSError as exc:
                self.socket.close()
                raise can.CanInitializationError(f"no bus at {channel}: {exc}") from exc
        # As python-can's SocketCAN bus does: the kernel dates each frame it receives.
        self.socket.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.channel_info = f"unix {channel}"
        super().__init__(channel=channel, **kwargs)

    def fileno(self) -> int:
        return self.socket.fileno()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        readable, _, _ = select.select([self.socket], [], [], timeout)
        if not readable:
            return None, False
        data = self.socket.recv(FRAME.size)
        if not data:
            raise can.CanOperationError("the other end closed the bus")
        can_id, length, payload = FRAME.unpack(data)
        message = can.Message(
            timestamp=time.time(),
            arbitration_id=can_id & 0x1FFFFFFF,
            is_extended_id=bool(can_id & EXTENDED),
            dlc=length,
            data=payload[:length],
        )
        return message, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        can_id = msg.arbitration_id | (EXTENDED if msg.is_extended_id else 0)
        try:
            self.socket.send(FRAME.pack(can_id, msg.dlc, bytes(msg.data)))
        except OSError as exc:
            raise can.CanOperationError(f"send: {exc}") from exc

    def shutdown(self) -> None:
        super().shutdown()
        self.socket.close()


def listening(channel: str) -> socket.socket:
    """A socket listening for the other end of ``channel`` (``accept`` it, then give it to
    ``UnixCanBus``); it waits ``ACCEPT_TIMEOUT_S`` at most."""
    server = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    server.bind(_address(channel))
    server.listen(1)
    server.settimeout(ACCEPT_TIMEOUT_S)
    return server


def _address(channel: str) -> str:
    return "\0busgate-bench-can-" + channel


def register() -> None:
    """``can.Bus(interface="socketcan")`` builds a ``UnixCanBus`` in this process."""
    can.interfaces.BACKENDS[INTERFACE] = (__name__, UnixCanBus.__name__)
