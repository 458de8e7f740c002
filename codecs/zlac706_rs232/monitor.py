"""The monitor reply as one state: eight frames assembled into a ``MonitorReply``.

The decoder emits one event per 4-byte frame rather than one per reply: each frame has its
own checksum, so a frame lost to noise costs that item only and never holds back or
corrupts the frames around it, the decoder stays stateless between frames (no timeout or
reply-boundary guess inside a sans-I/O decoder), and the bus owner already counts frames
(``ExpectedReply.frames`` = 8). The host gathers the eight events of one transaction and
calls ``assemble_monitor``. ``readings`` names one frame's item on its own.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from busgate.codecs.errors import CodecError
from busgate.codecs.registers import Reading
from busgate.codecs.zlac706_common import (
    AlarmFlags,
    amps_from_current_raw,
    rpm_from_speed_raw,
)
from busgate.codecs.zlac706_rs232.frames import MONITOR_FIELDS, PositionWord, Write
from busgate.codecs.zlac706_rs232.registers import REGISTERS, MonitorItem, join_position


@dataclass(frozen=True, slots=True)
class MonitorReply:
    """The driver's state as one monitor request reports it."""

    alarms: AlarmFlags
    voltage_v: int
    current_raw: int
    current_a: float
    speed_raw: int
    speed_rpm: float
    commanded_position_raw: int
    feedback_position_raw: int


def assemble_monitor(frames: Iterable[object]) -> MonitorReply:
    """One ``MonitorReply`` from the eight frames of a monitor reply, in any order.

    Raises ``CodecError`` naming the missing items when a frame is absent.

    >>> from busgate.codecs.zlac706_rs232.decoder import ReplyDecoder
    >>> decoder = ReplyDecoder()
    >>> decoder.feed(bytes.fromhex("80000181 e1001cfd e20011f3 e4010ef3"
    ...                            "e60000e6 e727101e e80000e8 e9271020"))
    >>> assemble_monitor(decoder.events())  # doctest: +NORMALIZE_WHITESPACE
    MonitorReply(alarms=<AlarmFlags.RUNNING: 1>, voltage_v=28, current_raw=17, current_a=0.17,
                 speed_raw=270, speed_rpm=98.876953125, commanded_position_raw=10000,
                 feedback_position_raw=10000)
    """
    raw: dict[int, int] = {}
    for frame in frames:
        if isinstance(frame, PositionWord):
            raw[frame.item] = frame.value
        else:
            item, name = MONITOR_FIELDS[type(frame)]
            raw[item] = getattr(frame, name)
    missing = [item.name for item in MonitorItem if item not in raw]
    if missing:
        raise CodecError(f"monitor reply incomplete: no {', '.join(missing)}")
    return MonitorReply(
        alarms=AlarmFlags(raw[MonitorItem.STATUS]),
        voltage_v=raw[MonitorItem.BUS_VOLTAGE],
        current_raw=raw[MonitorItem.CURRENT],
        current_a=amps_from_current_raw(raw[MonitorItem.CURRENT]),
        speed_raw=raw[MonitorItem.SPEED],
        speed_rpm=rpm_from_speed_raw(raw[MonitorItem.SPEED]),
        commanded_position_raw=join_position(
            raw[MonitorItem.COMMANDED_POSITION_HIGH], raw[MonitorItem.COMMANDED_POSITION_LOW]
        ),
        feedback_position_raw=join_position(
            raw[MonitorItem.FEEDBACK_POSITION_HIGH], raw[MonitorItem.FEEDBACK_POSITION_LOW]
        ),
    )


def readings(reply: object) -> list[Reading]:
    """The monitor item a reply frame carries, or the register a write sets, named and in
    its unit.

    Each monitor frame starts with its item's address. An ``Ack`` names the register written
    but carries no value, and names nothing here: ``[]``.

    >>> readings(PositionWord(MonitorItem.FEEDBACK_POSITION_LOW, 10000))  # 8.2.2 example
    [Reading(register='feedback_position_low', address=233, raw=10000, value=10000, unit='pulses')]
    >>> readings(Write(0x06, 273))  # 8.2.2: 100 rpm, truncated
    [Reading(register='speed', address=6, raw=273, value=99.975585938, unit='rpm')]
    """
    if isinstance(reply, Write):
        item, raw = reply.register, reply.value
    elif isinstance(reply, PositionWord):
        item, raw = reply.item, reply.value
    elif type(reply) in MONITOR_FIELDS:
        item, name = MONITOR_FIELDS[type(reply)]
        raw = int(getattr(reply, name))  # the status word as its bits, not as alarm names
    else:
        return []
    return REGISTERS.reading_at(item, raw)
