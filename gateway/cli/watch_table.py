"""The table ``busgate watch`` shows: the latest state of each device and statistics of each
bus, and how they are printed (a table redrawn in place on a terminal, ``name=value`` lines of
the rows that changed on a pipe).

Kept apart from ``client.py`` so that it knows no zenoh: zenoh's callback threads feed it
parsed JSON bodies (``update_state``, ``update_stats``, ``seed``) and the main thread reads it
(``render``, ``changed_lines``). Rules of this file: a callback only stores under the one
lock (a slow callback would stall every other one); the main thread takes a snapshot under it
and formats outside it; every cell is printed as a terminal may show it (``printable``: what
a gateway sends may carry a terminal's escapes), and a state of a shape no release sends
makes a row that says so (``(unreadable)``), never the end of the watch.

Each device shows its joint in SI (``JOINT``: a position joint's position in its unit, a
velocity joint's velocity in its unit per second, from the state's ``joint``) beside its raw
values (``MOTION``: measured → target, in the family's units, read through the family's joint
declaration, so that no family's field is named here). A joint's type is its state's, else
the type its family takes when a config names none (a gateway of an earlier release).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

from busgate.schemas.joints import (
    JOINT_NAME_CHARS,
    UNIT_CHARS,
    JointType,
    declaration_of,
    finite_or_none,
    type_told,
)
from busgate.schemas.validation import printable

#: The most of a value a cell shows (``printable``): a gateway may send a name or a value of
#: any length.
MOST_IN_A_CELL = 48

DEVICE_COLUMNS = (
    "device",
    "kind",
    "online",
    "stale",
    "power",
    "joint",
    "motion",
    "temp_c",
    "current_ma",
    "faults",
    "age",
)
BUS_COLUMNS = (
    "bus",
    "utilisation",
    "frames_s",
    "timeouts",
    "checksum_errors",
    "reconnects",
    "smallest_gap",
    "age",
)


class WatchTable:
    """The latest state of each device and statistics of each bus, keyed by (gateway, name)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._devices: dict[tuple[str, str], _Row] = {}
        self._buses: dict[tuple[str, str], _Row] = {}

    @property
    def empty(self) -> bool:
        with self._lock:
            return not self._devices and not self._buses

    def update_state(self, key: str, state: Any, now: float) -> None:
        """A sample of ``<prefix>/<gw>/dev/<device>/state``."""
        if isinstance(state, dict):
            self._store(self._devices, key, state, now)

    def update_stats(self, key: str, stats: Any, now: float) -> None:
        """A sample of ``<prefix>/<gw>/bus/<bus>/stats``; frames/s from the previous one."""
        if not isinstance(stats, dict):
            return
        with self._lock:
            previous = self._buses.get(_names(key))
        stats = {**stats, "frames_s": _frame_rate(previous.values if previous else None, stats)}
        self._store(self._buses, key, stats, now)

    def seed(self, info: dict[str, Any], wanted: Callable[[str], bool]) -> None:
        """Rows from an ``info`` reply, for devices and buses not heard from yet."""
        gateway = str(info.get("gateway", "?"))
        with self._lock:
            for bus in info.get("buses", []):
                name = str(bus.get("name", "?"))
                if wanted(f"{gateway}/bus/{name}/stats"):
                    self._buses.setdefault((gateway, name), _Row({}, None))
                for device in bus.get("devices", []):
                    state = device.get("state") if isinstance(device.get("state"), dict) else {}
                    row = _Row({"kind": device.get("kind"), **state}, None)
                    if wanted(f"{gateway}/dev/{device.get('name', '?')}/state"):
                        self._devices.setdefault((gateway, str(device.get("name"))), row)

    def render(self, now: float) -> list[str]:
        """The whole table, devices then buses."""
        devices, buses, several = self._snapshot()
        lines = _columns(
            _headers(DEVICE_COLUMNS, several),
            [_cells(k, r, _device_cells, now, several) for k, r in devices],
            "(no device seen)",
        )
        lines.append("")
        lines += _columns(
            _headers(BUS_COLUMNS, several),
            [_cells(k, r, _bus_cells, now, several) for k, r in buses],
            "(no bus seen)",
        )
        return lines

    def changed_lines(self, now: float) -> list[str]:
        """One ``name=value`` line per row updated since the last call (for a pipe)."""
        devices, buses, _ = self._snapshot()
        lines = []
        for rows, columns, cells in (
            (devices, DEVICE_COLUMNS, _device_cells),
            (buses, BUS_COLUMNS, _bus_cells),
        ):
            for (gateway, name), row in rows:
                if row.received is not None and row.received > row.reported:
                    row.reported = row.received
                    values = _cells((gateway, name), row, cells, now, several=False)
                    lines.append(
                        " ".join(
                            [f"gateway={gateway}"]
                            + [
                                f"{column}={printable(value, MOST_IN_A_CELL).replace(' ', '')}"
                                for column, value in zip(columns, values, strict=True)
                            ]
                        )
                    )
        return lines

    def _store(self, rows: dict, key: str, values: dict[str, Any], now: float) -> None:
        with self._lock:
            row = rows.get(_names(key))
            reported = row.reported if row else float("-inf")
            rows[_names(key)] = _Row(values, now, reported)

    def _snapshot(self) -> tuple[list, list, bool]:
        with self._lock:
            devices, buses = sorted(self._devices.items()), sorted(self._buses.items())
        several = len({gateway for (gateway, _), _ in devices + buses}) > 1
        return devices, buses, several


class _Row:
    __slots__ = ("received", "reported", "values")

    def __init__(
        self, values: dict[str, Any], received: float | None, reported: float = float("-inf")
    ) -> None:
        self.values, self.received, self.reported = values, received, reported


def _names(key: str) -> tuple[str, str]:
    """(gateway, name) of ``…/<gw>/dev/<name>/state`` or ``…/<gw>/bus/<name>/stats``."""
    parts = key.split("/")
    return parts[-4], parts[-2]


def _frame_rate(previous: dict[str, Any] | None, stats: dict[str, Any]) -> float | None:
    try:
        frames = stats["frames_out"] + stats["frames_in"]
        if previous is None or previous.get("uptime_s") is None:
            return frames / stats["uptime_s"] if stats["uptime_s"] > 0 else None
        elapsed = stats["uptime_s"] - previous["uptime_s"]
        before = previous["frames_out"] + previous["frames_in"]
        return (frames - before) / elapsed if elapsed > 0 else previous.get("frames_s")
    except (KeyError, TypeError):
        return None


def _device_cells(name: str, row: _Row, now: float) -> list[str]:
    state = row.values
    online = state.get("online")
    return [
        name,
        _text(state.get("kind")),
        "-" if online is None else ("yes" if online else "NO"),
        "STALE" if state.get("stale") else "-",
        _power(state),
        _joint(name, state, _joint_type(state)),
        _motion(state, _joint_type(state)),
        _text(state.get("temperature_c")),
        _text(state.get("current_ma")),
        _faults(state.get("faults")),
        _reading_age(row, now),
    ]


def _power(state: dict[str, Any]) -> str:
    """e-stopped (motion refused until re-enabled), enabled (the motor is driven), off."""
    if state.get("estopped"):
        return "e-stopped"
    enabled = state.get("enabled")
    return "-" if enabled is None else ("enabled" if enabled else "off")


def _reading_age(row: _Row, now: float) -> str:
    """How old the values are: the device's last reply, as of the state's arrival, plus the
    time since it arrived (a state repeats no reading as new: see the telemetry's ``ts``)."""
    age = row.values.get("last_reply_age_s")
    if row.received is None or not isinstance(age, int | float):
        return "-"
    return f"{age + max(0.0, now - row.received):.1f}s"


def _joint_type(state: dict[str, Any]) -> JointType:
    kind = state.get("kind")
    return type_told(kind if isinstance(kind, str) else "", state.get("joint"))


def _joint(device: str, state: dict[str, Any], joint_type: JointType) -> str:
    """The joint's value in SI with its unit: a position joint's position, a velocity joint's
    velocity (per second); its name before it when it is not the device's."""
    joint = state.get("joint")
    if not isinstance(joint, dict) or not isinstance(joint.get("unit"), str):
        return "-"
    unit = joint["unit"][:UNIT_CHARS]
    value = finite_or_none(joint.get(joint_type))
    shown = "-" if value is None else f"{_number(value)} {unit}"
    if joint_type == "velocity" and shown != "-":
        shown += "/s"
    name = joint.get("name")
    return (
        f"{name[:JOINT_NAME_CHARS]}: {shown}" if isinstance(name, str) and name != device else shown
    )


def _motion(state: dict[str, Any], joint_type: JointType) -> str:
    """The raw values: measured -> target, of the joint's position or (a velocity joint) of
    its speed in rpm, as the family names them."""
    kind = state.get("kind")
    declaration = declaration_of(kind) if isinstance(kind, str) else None
    if declaration is None:
        return "-"
    measured_field, target_field = declaration.raw_fields(joint_type)
    measured, target = state.get(measured_field), state.get(target_field)
    unit = " rpm" if measured_field == declaration.speed_rpm else ""
    if measured is None and target is None:
        return "-"
    shown = f"{_text(measured)}{unit}"
    return shown if target is None else f"{shown} -> {_text(target)}"


def _number(value: float) -> str:
    """Four significant digits, never in powers of ten above 1e-4: ``0.0051``, ``1.571``,
    ``1500``, ``123457``."""
    if value == 0:
        return "0"
    if abs(value) < 1e-4:
        return f"{value:.3g}"
    decimals = max(0, 3 - math.floor(math.log10(abs(value))))
    text = f"{value:.{decimals}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def _bus_cells(name: str, row: _Row, now: float) -> list[str]:
    stats = row.values
    utilisation, gap = stats.get("utilisation"), stats.get("smallest_gap_s")
    return [
        name,
        "-" if not isinstance(utilisation, int | float) else f"{utilisation * 100:.0f}%",
        _text(stats.get("frames_s")),
        _text(stats.get("timeouts")),
        _text(stats.get("checksum_errors")),
        _text(stats.get("reconnects")),
        "-" if not isinstance(gap, int | float) else f"{gap * 1000:.2f} ms",
        _age(row, now),
    ]


def _faults(faults: Any) -> str:
    return (",".join(map(str, faults)) or "-") if isinstance(faults, list) else _text(faults)


def _headers(columns: tuple[str, ...], several: bool) -> list[str]:
    return [c.upper() for c in ("gateway",) * several + columns]


def _cells(
    key: tuple[str, str], row: _Row, cells: Callable, now: float, several: bool
) -> list[str]:
    """A row's cells; a state of a shape no release sends (a number where a list goes) makes
    a row that says so, never the end of the watch."""
    try:
        made = cells(key[1], row, now)
    except (TypeError, ValueError, AttributeError, ArithmeticError):
        count = len(DEVICE_COLUMNS if cells is _device_cells else BUS_COLUMNS)
        made = [key[1], "(unreadable)", *["-"] * (count - 2)]
    return ([key[0]] if several else []) + made


def _columns(header: list[str], rows: list[list[str]], nothing: str) -> list[str]:
    """The rows in columns, each cell as a terminal may show it (``printable``): what a
    gateway sends is printed, and a name or value could carry a terminal's escapes."""
    if not rows:
        return [nothing]
    rows = [[printable(cell, MOST_IN_A_CELL) for cell in line] for line in rows]
    widths = [max(len(cell) for cell in column) for column in zip(header, *rows, strict=True)]
    return [
        "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
        for line in [header, *rows]
    ]


def _text(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.1f}"
    return str(value)


def _age(row: _Row, now: float) -> str:
    return "-" if row.received is None else f"{max(0.0, now - row.received):.1f}s"
