"""Time on the wire: the arithmetic and the per-protocol figures that deadlines, gaps and
bus budgets rest on.

UART frames are 8N1: 10 bits per byte (start, 8 data, stop). A classic CAN data frame with a
standard identifier has 47 fixed bits plus 8 per data byte; bit stuffing adds at most one bit
per four of the 34 + 8n bits it covers (SOF to CRC), which gives the worst case.

Each codec states its protocol's figures as ``TIMING``, a ``ProtocolTiming``: what its manual
says about turnaround and gaps, and where it says nothing, what we chose (the simulators and
the scheduler read the same figures).
"""

from __future__ import annotations

from dataclasses import dataclass

UART_BITS_PER_BYTE = 10


def uart_time(nbytes: int, baudrate: int) -> float:
    """Seconds ``nbytes`` take on an 8N1 UART at ``baudrate``.

    >>> round(uart_time(22, 921600) * 1e6)  # an Inspire LA status reply
    239
    """
    return nbytes * UART_BITS_PER_BYTE / baudrate


def can_frame_bits(data_bytes: int, *, worst_case: bool = True) -> int:
    """Bits of a classic CAN data frame with an 11-bit id, interframe space included.

    >>> can_frame_bits(8, worst_case=False), can_frame_bits(8)
    (111, 135)
    """
    bits = 47 + 8 * data_bytes
    if worst_case:
        bits += (34 + 8 * data_bytes - 1) // 4
    return bits


def can_time(data_bytes: int, bitrate: int, *, worst_case: bool = True) -> float:
    """Seconds one classic CAN frame with ``data_bytes`` takes at ``bitrate``.

    >>> round(can_time(8, 500_000) * 1e6)
    270
    """
    return can_frame_bits(data_bytes, worst_case=worst_case) / bitrate


@dataclass(frozen=True, slots=True)
class ProtocolTiming:
    """A device family's timing: least idle line between exchanges (``min_gap_s``, and the
    default a bus gets, ``default_gap_s``), the device's reply time range, and the default
    line speed (baud for UART, bit/s for CAN); ``rates``, the only line speeds the device
    can run at, when its manual names them (empty: any the bus takes)."""

    min_gap_s: float
    default_gap_s: float
    reply_min_s: float
    reply_max_s: float
    default_rate: int
    rates: tuple[int, ...] = ()
