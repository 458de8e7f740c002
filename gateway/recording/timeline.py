"""The wire as a picture: an incident file's frames, bus by bus, on one time axis, as SVG
(``busgate record --timeline``).

Why: what went wrong on a bus is a matter of moments (a gap under the manual's 1 ms, a follow
tick late, the e-stop's frame behind an exchange), and a list of timestamps hides them where
a picture shows them at once. The picture is made of what the flight recorder wrote: each
frame's host time (a UART write when it returned, a read when its bytes came; a CAN frame at
its arrival) and its bytes, so every figure on it is the host's view of the wire.

Rules of this file:

1. The file is a peer's word: a frame message that is not the recorder's shape (nested past
   what the JSON reader takes too) is left out and counted, never an exception; at most
   ``MAX_FRAMES`` frames are drawn (a longer window is refused, asking for a shorter one)
   and ``MAX_MARKS`` e-stops marked, so no file makes a picture without end; its text is
   escaped, and what XML cannot hold (control characters, lone surrogates) is drawn as
   U+FFFD (``_text``), so the picture is always one a viewer reads.
2. Drawing is pure (``svg``: a window in, SVG text out); reading the file is
   ``window_of``'s, the command line ``cli.record``'s.
3. The figures beside each lane are the host's: the smallest time from a frame received to
   the next one sent (the line's idle gap as the host saw it) and the median time between
   two frames sent.
"""

from __future__ import annotations

import datetime
import itertools
import json
import math
import re
import statistics
from collections.abc import Iterable
from dataclasses import dataclass
from html import escape
from typing import IO

from busgate.gateway.recording import mcap_log

#: The most frames one picture draws, and e-stops it marks (rule 1).
MAX_FRAMES = 20_000
MAX_MARKS = 100
#: What XML 1.0 cannot hold: control characters but tab and newlines, lone surrogates, and
#: the two non-characters U+FFFE and U+FFFF (rule 1).
NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")
#: The picture's geometry, in pixels.
WIDTH, LEFT, RIGHT, TOP, LANE, AXIS = 1000, 110, 20, 40, 80, 40
#: Steps the time axis is ticked at (ms): the first that gives at most ``MAX_TICKS`` ticks.
TICK_STEPS_MS = (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)
MAX_TICKS = 12
TX_COLOUR, RX_COLOUR, MARK_COLOUR = "#1f6fb4", "#e07b00", "#c8102e"


@dataclass(frozen=True, slots=True)
class WireFrame:
    """One frame (or one UART read) as recorded: host wall time (s), sent or received, and
    its text (hex bytes, or a CAN frame as ``cansend`` writes it)."""

    ts: float
    sent: bool
    wire: str


@dataclass(frozen=True, slots=True)
class Window:
    """What one picture shows: ``start`` to ``end`` (wall s), each bus's frames in it, and
    the e-stops that came in it (when each came); ``left_out``: frame messages of the file that
    were not the recorder's shape (rule 1)."""

    start: float
    end: float
    frames: dict[str, list[WireFrame]]
    estops: list[float]
    left_out: int


def window_of(stream: IO[bytes], span_s: float, end: float | None = None) -> Window:
    """The ``span_s`` of ``stream``'s frames ending at ``end`` (wall s); by default a fifth of
    the span after the file's first e-stop, else at its last frame. ``ValueError`` past
    ``MAX_FRAMES`` frames in it (rule 1), or the ``mcap`` reader's own errors."""
    if end is None:
        first_estop, last = math.inf, -math.inf
        for message in mcap_log.messages(stream):
            if _is_frames(message.topic):
                last = max(last, message.log_time_ns / 1e9)
            elif _is_estop(message):
                first_estop = min(first_estop, message.log_time_ns / 1e9)
        end = first_estop + span_s / 5 if math.isfinite(first_estop) else last
    start = end - span_s
    frames: dict[str, list[WireFrame]] = {}
    marks: set[float] = set()
    left_out = drawn = 0
    for message in mcap_log.messages(stream):
        if not start <= message.log_time_ns / 1e9 <= end:
            continue
        if _is_estop(message) and len(marks) < MAX_MARKS:
            marks.add(message.log_time_ns / 1e9)
        if not _is_frames(message.topic):
            continue
        parsed = _frame(message.data)
        if parsed is None:
            left_out += 1
            continue
        bus, frame = parsed
        drawn += 1
        if drawn > MAX_FRAMES:
            raise ValueError(
                f"more than {MAX_FRAMES} frames in {span_s * 1e3:g} ms: ask for a shorter span"
            )
        frames.setdefault(bus, []).append(frame)
    return Window(start, end, frames, sorted(marks), left_out)


def _is_frames(topic: str) -> bool:
    return topic.endswith("/frames") and "/bus/" in topic


def _is_estop(message: mcap_log.Recorded) -> bool:
    """Whether ``message`` is an e-stop the gateway was sent (a command on an e-stop key),
    dated by its arrival: the frames it caused come after it."""
    if not message.topic.endswith("/commands"):
        return False
    try:
        body = json.loads(message.data)
    except (ValueError, RecursionError):
        return False
    return isinstance(body, dict) and str(body.get("key", "")).endswith("/estop")


def _frame(data: bytes) -> tuple[str, WireFrame] | None:
    """A frame message's bus and frame, ``None`` when it is not the recorder's shape."""
    try:
        body = json.loads(data)
    except (ValueError, RecursionError):
        return None
    if not isinstance(body, dict):
        return None
    ts, bus, direction, wire = (body.get(key) for key in ("ts", "bus", "dir", "wire"))
    if not (isinstance(ts, float | int) and math.isfinite(ts) and isinstance(bus, str)):
        return None
    if direction not in ("tx", "rx") or not isinstance(wire, str):
        return None
    return _text(bus), WireFrame(float(ts), direction == "tx", _text(wire))


def smallest_gap_s(frames: Iterable[WireFrame]) -> float | None:
    """The least time from a frame received to the next frame sent (rule 3)."""
    gaps, received = [], None
    for frame in frames:
        if not frame.sent:
            received = frame.ts
        elif received is not None:
            gaps.append(frame.ts - received)
            received = None
    return min(gaps, default=None)


def median_period_s(frames: Iterable[WireFrame]) -> float | None:
    """The median time between two frames sent (rule 3)."""
    sent = [frame.ts for frame in frames if frame.sent]
    steps = [later - earlier for earlier, later in itertools.pairwise(sent)]
    return statistics.median(steps) if steps else None


def svg(window: Window) -> str:
    """The window as an SVG picture: a lane a bus, frames sent above its line and frames
    received below, e-stops as red lines across every lane, the time axis in ms."""
    buses = sorted(window.frames)
    height = TOP + LANE * max(len(buses), 1) + AXIS
    span = window.end - window.start
    plot = WIDTH - LEFT - RIGHT

    def x(ts: float) -> float:
        return LEFT + plot * (ts - window.start) / span

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" '
        f'font-family="sans-serif" font-size="12">',
        f'<rect width="{WIDTH}" height="{height}" fill="white"/>',
        f'<text x="{LEFT}" y="18">from {_utc(window.start)}: frames sent (above each line, '
        f"blue) and received (below, orange), an e-stop's arrival in red; host time</text>",
    ]
    for lane, bus in enumerate(buses):
        out.extend(_lane(bus, window.frames[bus], TOP + LANE * lane, x))
    out.extend(_axis(span, TOP + LANE * max(len(buses), 1), x, window.start))
    for ts in window.estops:
        out.append(
            f'<line class="estop" x1="{x(ts):.1f}" x2="{x(ts):.1f}" y1="{TOP}" '
            f'y2="{height - AXIS}" stroke="{MARK_COLOUR}" stroke-width="2"/>'
        )
        out.append(f'<text x="{x(ts) + 3:.1f}" y="{TOP - 6}" fill="{MARK_COLOUR}">e-stop</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _utc(ts: float) -> str:
    moment = datetime.datetime.fromtimestamp(ts, datetime.UTC)
    return moment.strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _lane(bus: str, frames: list[WireFrame], top: float, x) -> list[str]:
    middle = top + LANE / 2
    gap, period = smallest_gap_s(frames), median_period_s(frames)
    figures = []
    if gap is not None:
        figures.append(f"received → sent ≥ {gap * 1e3:.2f} ms")
    if period is not None:
        figures.append(f"sent every {period * 1e3:.2f} ms (median)")
    out = [
        f'<g class="lane" data-bus="{escape(bus)}">',
        f'<text x="8" y="{middle - 4:.1f}" font-weight="bold">{escape(bus)}</text>',
        f'<text x="8" y="{middle + 12:.1f}" font-size="10">{len(frames)} frames</text>',
        f'<text x="{WIDTH - RIGHT}" y="{top + 12:.1f}" font-size="10" text-anchor="end">'
        f"{', '.join(figures)}</text>",
        f'<line x1="{LEFT}" x2="{WIDTH - RIGHT}" y1="{middle}" y2="{middle}" stroke="#999"/>',
    ]
    for frame in frames:
        y, colour = (middle - 22, TX_COLOUR) if frame.sent else (middle + 2, RX_COLOUR)
        direction = "sent" if frame.sent else "received"
        out.append(
            f'<rect class="{"tx" if frame.sent else "rx"}" x="{x(frame.ts) - 1:.1f}" '
            f'y="{y:.1f}" width="2" height="20" fill="{colour}"><title>{direction} '
            f"{frame.ts:.6f}: {escape(frame.wire)}</title></rect>"
        )
    out.append("</g>")
    return out


def _axis(span: float, top: float, x, start: float) -> list[str]:
    step_ms = next(
        (step for step in TICK_STEPS_MS if span * 1e3 / step <= MAX_TICKS), TICK_STEPS_MS[-1]
    )
    out = [f'<line x1="{LEFT}" x2="{WIDTH - RIGHT}" y1="{top}" y2="{top}" stroke="black"/>']
    for tick in range(math.floor(span * 1e3 / step_ms) + 1):
        at = start + tick * step_ms / 1e3
        out.append(
            f'<line x1="{x(at):.1f}" x2="{x(at):.1f}" y1="{top}" y2="{top + 5}" stroke="black"/>'
        )
        out.append(
            f'<text x="{x(at):.1f}" y="{top + 18}" text-anchor="middle">'
            f"{tick * step_ms:g} ms</text>"
        )
    return out


def _text(value: str) -> str:
    """A frame's text with what XML cannot hold as U+FFFD (rule 1), as read: the picture's
    text and the command's line are then always encodable (a lone surrogate is not)."""
    return NOT_XML.sub("\ufffd", value)
