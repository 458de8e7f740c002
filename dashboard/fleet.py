"""What the dashboard knows of the fleet: every gateway up, its buses and devices, each
device's latest state and the last minute of what its plots show, each base's latest odometry
and its recent track, the events; and, since the browsers were last told, what changed
(``drain``).

Rules of this file:

1. Fed from zenoh's threads, read from the server's loop: every method takes the lock, does
   no I/O and returns at once.
2. Nothing here trusts a sample. A gateway's data is taken only while its liveliness token is
   up (a sample that arrives after it went does not bring it back), a device's state only for
   a device the gateway's ``info`` lists, a plotted value only when it is a finite number; a
   payload that is not the JSON object it should be is dropped, and one nested deeper than
   ``CLEAN_DEPTH`` is cut there. What is kept is bounded: at most ``MAX_GATEWAYS`` gateways
   (one refused for that is taken when another goes: ``Feed``), ``MAX_BUSES`` buses and
   ``MAX_DEVICES`` devices each, names of ``NAME_CHARS`` at most, ``HISTORY_S`` of samples
   per device, ``EVENTS_KEPT`` events.
3. A plot sample is taken at most every ``SAMPLE_EVERY_S`` per device (the latest state
   wins): the browser draws a minute of them for every device, at 50 devices too. A sample
   more than ``CLOCK_STEP_S`` older than the last one kept (the gateway's clock was set
   back, or a state came stamped in the future) starts the device's history again, and the
   browsers start theirs again (``restart``, as a base's track).
4. What the browsers get is JSON made of what came in, under the dashboard's own names:
   ``snapshot()`` for a browser that just connected, ``drain()`` for the others since.
5. A device is shown as its joint, in SI (``JointView``): a position joint's position, a
   velocity joint's velocity, and its target, as its state's ``joint`` says them. A state
   without a ``joint`` (a gateway of an earlier release) is plotted raw, as the family's
   joint declaration reads it (``busgate.schemas.joints``), so no family's field is named
   here; a joint that is malformed leaves its values ``None``, never the page broken.
6. A base is known by its odometry alone (``info`` does not list bases): it appears with its
   first message that is an ``Odometry`` (``busgate.schemas.bases``) naming the base its key
   names, at most ``MAX_BASES`` a gateway. Its track is its recent ``(x, y)``: a point kept
   once the base is ``TRACK_STEP_M`` from the last one kept, at most ``TRACK_POINTS``. When the
   pose jumps (farther than its measured speed takes it: its odometry was reset, its gateway
   restarted), the track starts again from there, and the browsers start theirs again. The
   twist told as measured is the odometry's own (the gateway measures it over 0.1 s at
   least: ``busgate.gateway.base.kinematics`` rule 4).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from busgate.schemas.bases import Odometry
from busgate.schemas.joints import (
    JOINT_NAME_CHARS,
    UNIT_CHARS,
    declaration_of,
    finite_or_none,
    type_told,
)

HISTORY_S = 60.0
SAMPLE_EVERY_S = 0.05
EVENTS_KEPT = 500
MAX_GATEWAYS = 256
MAX_BUSES = 64
MAX_DEVICES = 512
#: The longest gateway, bus or device name kept (a config's names are far shorter).
NAME_CHARS = 128
#: How deep a payload's JSON is read: a state is some four levels deep.
CLEAN_DEPTH = 16
#: A sample this much older than the last one kept starts the history again (rule 3).
CLOCK_STEP_S = 1.0
MAX_BASES = 64
#: A base's track (rule 6): at most ``TRACK_POINTS`` points, each ``TRACK_STEP_M`` from the
#: one before (600 cm-steps at the finest: a base at rest adds none).
TRACK_POINTS = 600
TRACK_STEP_M = 0.01
#: Between two odometry messages, a pose that moved farther than twice what the base's
#: measured speed (the greater of the two messages') takes it in the time between them, and
#: ``JUMP_M`` more, jumped rather than moved (rule 6).
JUMP_M = 0.05


def clean(value: Any, depth: int = CLEAN_DEPTH) -> Any:
    """``value`` with every non-finite float made ``None`` (JSON has no NaN, and a browser's
    ``JSON.parse`` refuses the whole message that carries one), and what is nested deeper
    than ``depth`` too (rule 2: it would exhaust the interpreter's stack)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict | list) and depth <= 0:
        return None
    if isinstance(value, dict):
        return {key: clean(item, depth - 1) for key, item in value.items()}
    if isinstance(value, list):
        return [clean(item, depth - 1) for item in value]
    return value


def _named(entry: dict[str, Any]) -> bool:
    """Whether an info's bus or device has a name the dashboard keeps (rule 2)."""
    name = entry.get("name")
    return isinstance(name, str) and 0 < len(name) <= NAME_CHARS


def _text(value: Any, most: int) -> str | None:
    return value[:most] if isinstance(value, str) else None


@dataclass(frozen=True, slots=True)
class JointView:
    """What a device's row and plot show of its joint, in SI, from one state: its value (a
    position joint's position, a velocity joint's velocity) and target, its velocity and
    effort, each with its unit."""

    name: str | None
    type: str
    unit: str | None
    value: float | None
    target: float | None
    velocity: float | None
    effort: float | None
    effort_unit: str | None

    @classmethod
    def of(cls, kind: str, state: dict[str, Any]) -> JointView | None:
        """The view of ``state`` (distrusted) of a device of ``kind``; ``None`` when the
        state carries no joint object (rule 5)."""
        values = state.get("joint")
        if not isinstance(values, dict):
            return None
        declaration = declaration_of(kind)
        joint_type = type_told(kind, values)
        return cls(
            _text(values.get("name"), JOINT_NAME_CHARS),
            joint_type,
            _text(values.get("unit"), UNIT_CHARS),
            finite_or_none(values.get(joint_type)),
            finite_or_none(values.get("target")),
            finite_or_none(values.get("velocity")),
            finite_or_none(values.get("effort")),
            None if declaration is None else declaration.effort_unit,
        )

    def told(self) -> dict[str, Any]:
        """The view as a browser gets it: values with their units."""
        unit = self.unit or ""
        value_unit = f"{unit}/s" if self.type == "velocity" else unit
        return {
            "name": self.name,
            "type": self.type,
            "value": self.value,
            "value_unit": value_unit,
            "target": self.target,
            "velocity": self.velocity,
            "velocity_unit": f"{unit}/s",
            "effort": self.effort,
            "effort_unit": self.effort_unit,
        }


def _raw_sample(kind: str, state: dict[str, Any]) -> tuple[float | None, float | None]:
    """The raw value and target of a state that carries no joint (rule 5)."""
    declaration = declaration_of(kind)
    if declaration is None:
        return None, None
    measured, target = declaration.raw_fields(declaration.types[0])
    return finite_or_none(state.get(measured)), finite_or_none(state.get(target))


def sample_of(kind: str, state: dict[str, Any]) -> list[float | None] | None:
    """``[ts, joint value, joint target, current_ma]`` of a state; ``None`` without a time."""
    ts = finite_or_none(state.get("ts"))
    if ts is None:
        return None
    view = JointView.of(kind, state)
    value, target = _raw_sample(kind, state) if view is None else (view.value, view.target)
    return [ts, value, target, finite_or_none(state.get("current_ma"))]


class Device:
    """One device: its kind, bus, latest state and plot samples."""

    def __init__(self, kind: str, bus: str) -> None:
        self.kind, self.bus = kind, bus
        self.state: dict[str, Any] | None = None
        self.samples: deque[list[float | None]] = deque()
        self.pending: list[list[float | None]] = []  # samples the browsers have not had
        self.last_sample_at = -math.inf
        self.restarted = False  # since the last drain: the browsers start their history again

    def take(self, state: dict[str, Any]) -> None:
        self.state = state
        sample = sample_of(self.kind, state)
        if sample is None:
            return
        ts = sample[0]
        assert ts is not None
        if ts < self.last_sample_at - CLOCK_STEP_S:  # rule 3: a clock set back
            self.samples.clear()
            self.pending.clear()
            self.last_sample_at = -math.inf
            self.restarted = True
        if ts - self.last_sample_at < SAMPLE_EVERY_S and self.samples:
            self.samples[-1] = sample  # rule 3: the latest of the interval
            if self.pending:
                self.pending[-1] = sample
            else:
                self.pending.append(sample)
        else:
            self.samples.append(sample)
            self.pending.append(sample)
            self.last_sample_at = ts
        while self.samples and self.samples[0][0] < ts - HISTORY_S:  # type: ignore[operator]
            self.samples.popleft()


class Base:
    """One base: its latest odometry and its track, ``[ts, x, y]`` points (rule 6)."""

    def __init__(self) -> None:
        self.odometry: dict[str, Any] | None = None
        self.track: deque[list[float]] = deque(maxlen=TRACK_POINTS)
        self.pending: list[list[float]] = []  # points the browsers have not had
        self.restarted = False  # since the last drain: the browsers start their track again
        self.measured: dict[str, float | None] = {"linear": None, "angular": None}
        self._last: _Pose | None = None  # the last message's

    def take(self, odometry: dict[str, Any]) -> None:
        self.odometry = odometry
        ts, x, y, linear, angular = (
            finite_or_none(odometry.get(name)) for name in ("ts", "x", "y", "linear", "angular")
        )
        self.measured = {"linear": linear, "angular": angular}
        if ts is None or x is None or y is None:
            return
        pose = _Pose(ts, x, y, math.inf if linear is None else abs(linear))
        if self._last is not None and _jumped(self._last, pose):
            self.track.clear()
            self.pending = []
            self.restarted = True
        self._last = pose
        if self.track and math.dist(self.track[-1][1:], (x, y)) < TRACK_STEP_M:
            return
        point = [ts, x, y]
        self.track.append(point)
        self.pending.append(point)
        del self.pending[:-TRACK_POINTS]


@dataclass(frozen=True, slots=True)
class _Pose:
    ts: float
    x: float
    y: float
    speed: float  # |linear| as measured; ``inf`` when unknown: never taken for a jump


def _jumped(before: _Pose, after: _Pose) -> bool:
    """The pose went from ``before`` to ``after`` farther than the base drove (``JUMP_M``)."""
    distance = math.dist((before.x, before.y), (after.x, after.y))
    reach = 2 * max(before.speed, after.speed) * max(after.ts - before.ts, 0.0)
    return distance > JUMP_M + reach


def odometry_of(base: str, body: Any) -> dict[str, Any] | None:
    """``body`` as the dashboard keeps it when it is an ``Odometry`` of ``base`` (non-finite
    numbers made ``None``); else ``None``."""
    try:
        odometry = Odometry.model_validate(body)
    except ValidationError:
        return None
    return clean(odometry.model_dump()) if odometry.base == base else None


class Gateway:
    """One gateway up: its version, buses (with their last statistics), devices and bases."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.version: str | None = None
        self.buses: dict[str, dict[str, Any]] = {}
        self.devices: dict[str, Device] = {}
        self.bases: dict[str, Base] = {}

    def view(self) -> dict[str, Any]:
        """The gateway as the page lists it (without device states)."""
        return {
            "name": self.name,
            "version": self.version,
            "buses": [
                {
                    "name": name,
                    **bus,
                    "devices": [d for d, v in self.devices.items() if v.bus == name],
                }
                for name, bus in self.buses.items()
            ],
        }


class Fleet:
    """Every gateway up, and what changed since the last ``drain``."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._gateways: dict[str, Gateway] = {}
        self._events: deque[dict[str, Any]] = deque(maxlen=EVENTS_KEPT)
        self._changed_gateways: set[str] = set()
        self._gone: set[str] = set()
        self._changed_states: set[tuple[str, str]] = set()
        self._changed_bases: set[tuple[str, str]] = set()
        self._new_events: list[dict[str, Any]] = []

    # -- what comes in (zenoh's threads) ---------------------------------------------------------

    def gateway_up(self, name: str) -> bool:
        """A gateway's token came: ``True`` when it is new here (its ``info`` is wanted);
        ``False`` too when ``MAX_GATEWAYS`` are (``full``)."""
        with self._lock:
            if name in self._gateways or len(self._gateways) >= MAX_GATEWAYS:
                return False
            self._gateways[name] = Gateway(name)
            self._gone.discard(name)
            self._changed_gateways.add(name)
            return True

    def has(self, name: str) -> bool:
        with self._lock:
            return name in self._gateways

    @property
    def full(self) -> bool:
        """Whether ``MAX_GATEWAYS`` gateways are shown: another waits for one to go."""
        with self._lock:
            return len(self._gateways) >= MAX_GATEWAYS

    def gateway_gone(self, name: str) -> None:
        with self._lock:
            if self._gateways.pop(name, None) is None:
                return
            self._changed_gateways.discard(name)
            self._changed_states = {k for k in self._changed_states if k[0] != name}
            self._changed_bases = {k for k in self._changed_bases if k[0] != name}
            self._gone.add(name)

    def info(self, name: str, info: Any) -> None:
        """The gateway's ``info`` answer: its version, buses and devices (with their last
        states); a malformed one is dropped."""
        buses = info.get("buses") if isinstance(info, dict) else None
        if not isinstance(buses, list):
            return
        buses = clean(buses)
        with self._lock:
            gateway = self._gateways.get(name)
            if gateway is None:
                return
            version = info.get("version")
            gateway.version = version if isinstance(version, str) else None
            for bus in buses:
                self._take_bus(gateway, bus)
            self._changed_gateways.add(name)

    def _take_bus(self, gateway: Gateway, bus: Any) -> None:
        if not isinstance(bus, dict) or not _named(bus):
            return
        if bus["name"] not in gateway.buses and len(gateway.buses) >= MAX_BUSES:
            return
        gateway.buses.setdefault(bus["name"], {"protocol": str(bus.get("protocol")), "stats": None})
        for device in bus.get("devices") or ():
            if not isinstance(device, dict) or not _named(device):
                continue
            if device["name"] not in gateway.devices and len(gateway.devices) < MAX_DEVICES:
                gateway.devices[device["name"]] = Device(str(device.get("kind")), bus["name"])
            if isinstance(device.get("state"), dict):
                self._take_state(gateway, device["name"], device["state"])

    def state(self, gateway: str, device: str, state: Any) -> None:
        if not isinstance(state, dict):
            return
        state = clean(state)
        with self._lock:
            found = self._gateways.get(gateway)
            if found is not None:
                self._take_state(found, device, state)

    def _take_state(self, gateway: Gateway, name: str, state: dict[str, Any]) -> None:
        device = gateway.devices.get(name)
        if device is not None:
            device.take(state)
            self._changed_states.add((gateway.name, name))

    def odometry(self, gateway: str, base: str, body: Any) -> None:
        """A base's odometry (rule 6): the base appears with its first."""
        odometry = odometry_of(base, body)
        if odometry is None:
            return
        with self._lock:
            found = self._gateways.get(gateway)
            if found is None:
                return
            kept = found.bases.get(base)
            if kept is None:
                if len(found.bases) >= MAX_BASES:
                    return
                kept = found.bases[base] = Base()
            kept.take(odometry)
            self._changed_bases.add((gateway, base))

    def stats(self, gateway: str, bus: str, stats: Any) -> None:
        """A bus's statistics, with its frames per second since the previous ones."""
        if not isinstance(stats, dict):
            return
        stats = clean(stats)
        with self._lock:
            found = self._gateways.get(gateway)
            if found is None or bus not in found.buses:
                return
            kept = found.buses[bus]
            kept["frames_per_s"] = _rate(kept.get("stats"), stats)
            kept["stats"] = stats
            self._changed_gateways.add(gateway)

    def event(self, gateway: str, event: Any) -> None:
        if not isinstance(event, dict):
            return
        event = clean(event)
        with self._lock:
            if gateway not in self._gateways:
                return
            entry = {"gateway": gateway, "event": event}
            self._events.append(entry)
            self._new_events.append(entry)
            del self._new_events[:-EVENTS_KEPT]

    # -- what goes out (the server's loop) -------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """Everything, for a browser that just connected."""
        with self._lock:
            return {
                "now": self._clock(),
                "gateways": [g.view() for g in self._gateways.values()],
                "devices": [
                    _device_view(g.name, name, device, list(device.samples), restart=True)
                    for g in self._gateways.values()
                    for name, device in g.devices.items()
                ],
                "bases": [
                    _base_view(g.name, name, base, list(base.track), restart=True)
                    for g in self._gateways.values()
                    for name, base in g.bases.items()
                ],
                "events": list(self._events),
            }

    def drain(self) -> dict[str, Any] | None:
        """What changed since the last drain (``None``: nothing did)."""
        with self._lock:
            if not (
                self._changed_gateways
                or self._gone
                or self._changed_states
                or self._changed_bases
                or self._new_events
            ):
                return None
            devices = []
            for gateway_name, name in sorted(self._changed_states):
                device = self._gateways[gateway_name].devices[name]
                devices.append(
                    _device_view(gateway_name, name, device, device.pending, device.restarted)
                )
                device.pending, device.restarted = [], False
            bases = []
            for gateway_name, name in sorted(self._changed_bases):
                base = self._gateways[gateway_name].bases[name]
                bases.append(_base_view(gateway_name, name, base, base.pending, base.restarted))
                base.pending, base.restarted = [], False
            delta = {
                "now": self._clock(),
                "gateways": [self._gateways[g].view() for g in sorted(self._changed_gateways)],
                "gone": sorted(self._gone),
                "devices": devices,
                "bases": bases,
                "events": self._new_events,
            }
            self._changed_gateways, self._gone, self._changed_states = set(), set(), set()
            self._changed_bases = set()
            self._new_events = []
            return delta


def _device_view(
    gateway: str, name: str, device: Device, samples: list[list[float | None]], restart: bool
) -> dict[str, Any]:
    """A device as a browser gets it: its state, its joint, and its plot samples (those since
    the last drain; all of them with ``restart``, which says to drop what it has: rule 3)."""
    view = None if device.state is None else JointView.of(device.kind, device.state)
    return {
        "gateway": gateway,
        "device": name,
        "kind": device.kind,
        "bus": device.bus,
        "state": device.state,
        "joint": None if view is None else view.told(),
        "samples": samples,
        "restart": restart,
    }


def _base_view(
    gateway: str, name: str, base: Base, track: list[list[float]], restart: bool
) -> dict[str, Any]:
    """A base as a browser gets it: its latest odometry, its twist as measured (rule 6), and
    its track's points (those since the last drain; all of them with ``restart``, which says
    to drop what it has)."""
    return {
        "gateway": gateway,
        "base": name,
        "odometry": base.odometry,
        "measured": base.measured,
        "track": track,
        "restart": restart,
    }


def _rate(before: Any, after: dict[str, Any]) -> float | None:
    """Frames (out and in) per second between two statistics of one bus."""
    if not isinstance(before, dict):
        return None
    try:
        frames = (after["frames_out"] + after["frames_in"]) - (
            before["frames_out"] + before["frames_in"]
        )
        elapsed = after["ts"] - before["ts"]
        rate = frames / elapsed if elapsed > 0 else None
    except (KeyError, TypeError, OverflowError):
        return None
    return finite_or_none(rate)
