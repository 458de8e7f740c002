"""Time on the wire: the arithmetic and the per-protocol figures that deadlines, gaps and
bus budgets rest on.

UART frames are 8N1: 10 bits per byte (start, 8 data, stop). A classic CAN data frame with a
standard identifier has 47 fixed bits plus 8 per data byte; bit stuffing adds at most one bit
per four of the 34 + 8n bits it covers (SOF to CRC), which gives the worst case.

``PROTOCOL_TIMING`` holds what the manuals say about turnaround and gaps, and marks where they
say nothing and we chose (the simulators and the scheduler read the same figures).
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
    line speed (baud for UART, bit/s for CAN)."""

    min_gap_s: float
    default_gap_s: float
    reply_min_s: float
    reply_max_s: float
    default_rate: int


PROTOCOL_TIMING: dict[str, ProtocolTiming] = {
    # Manual 3.4.2: replies after 120 µs, up to 800 µs when a control task interrupts;
    # "keep commands at least 1 ms apart". 921600 baud is the D-type factory default.
    "inspire_la": ProtocolTiming(0.001, 0.001, 120e-6, 800e-6, 921_600),
    # The DS manual states no reply time, gap or baud rate: we assume a reply within 500 µs,
    # ask no minimum gap of the protocol, default to 0.5 ms of idle line and 115200 baud.
    "ds_servo": ProtocolTiming(0.0, 0.0005, 50e-6, 500e-6, 115_200),
    # The ZLAC706 manual states no RS232 baud rate or acknowledgement time: we assume an
    # acknowledgement within 1 ms and default to 115200 baud; the bus config names the rate.
    "zlac706_rs232": ProtocolTiming(0.0, 0.0005, 100e-6, 1e-3, 115_200),
    # CAN arbitrates the bus itself, so no gap; the manual gives 500 kbit/s and no reply time.
    "zlac706_can": ProtocolTiming(0.0, 0.0, 100e-6, 1e-3, 500_000),
}
