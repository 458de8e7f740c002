"""The gateway as ``diagnostic_msgs/DiagnosticArray``: one status per joint and one per bus,
what ``rqt_robot_monitor`` and a fleet's diagnostic aggregator read.

Rules of this file:

1. A joint's level: STALE when its device was never read, ERROR when it is offline, faulted
   or e-stopped, STALE when its reading is stale, WARN when the face's last command for it
   was refused (claimed by another client, e-stopped …), else OK. Its message says the worst
   reason in words; its values say all of them (online, stale, faults, e-stopped, claimed by,
   the last refusal).
2. A bus's level: ERROR when it is down, WARN when it timed out or saw bad checksums since
   the last status, else OK; its values are its counters and utilisation.
3. Names are ``<node>: joint <name>`` and ``<node>: bus <name>``; ``hardware_id`` is the
   device's (``<kind> id <n> on bus <bus>``) or the bus's name.
4. One more status, ``<node>: commands``, is WARN once commands have named joints the gateway
   does not have (each is told in the log once), naming them, each in quotes (an empty name
   is ``''``): a controller's config that names them needs fixing. It is WARN too while the
   last message refused named no joint of the gateway (no names, or only names no joint
   has: no joint's status can show it), saying why.
5. One more, ``<node>: input``, is WARN when the node dropped samples or requests since the
   last status (``node`` rule 2: not the type's CDR, without rmw_zenoh's attachment, on a
   wildcard, too large), naming each topic or service that dropped and its last reason; its
   values are the count since the start, each such topic's or service's among them.
6. Pure: states, statistics and refusals in, the message out.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True, slots=True)
class JointHealth:
    """What the diagnostics say of one joint."""

    joint: str
    device: str
    hardware_id: str
    state: dict[str, Any] | None  # the device's latest state; None: never read
    claimed_by: str | None
    refusal: str | None  # the face's last refused command for it, in one line


@dataclass(frozen=True, slots=True)
class BusHealth:
    """What the diagnostics say of one bus."""

    bus: str
    up: bool
    stats: dict[str, Any]
    new_errors: int  # timeouts and bad checksums since the last status


@dataclass(frozen=True, slots=True)
class Dropped:
    """What one topic or service of the node dropped (rule 5)."""

    entity: str
    count: int  # since the start
    new: int  # since the last status
    last: str  # the last one, in words


def diagnostic_array(
    node: str,
    stamp: dict[str, int],
    joints: list[JointHealth],
    buses: list[BusHealth],
    unknown: Iterable[str] = (),
    dropped: Iterable[Dropped] = (),
    refusal: str | None = None,
) -> dict[str, Any]:
    """The message (the rules above); ``unknown``: the joint names commands gave that no
    joint has, and ``refusal``: the last refused message's, when it named no joint (rule 4);
    ``dropped``: each topic or service that dropped any (rule 5)."""
    return {
        "header": {"stamp": stamp, "frame_id": ""},
        "status": [_joint_status(node, j) for j in joints]
        + [_bus_status(node, b) for b in buses]
        + [_commands_status(node, sorted(unknown), refusal), _input_status(node, list(dropped))],
    }


def _input_status(node: str, dropped: list[Dropped]) -> dict[str, Any]:
    lately = [f"{d.entity}: {d.new}, the last {d.last}" for d in dropped if d.new]
    if lately:
        level, message = WARN, f"dropped in the last second: {'; '.join(lately)}"
    else:
        level, message = OK, "ok"
    values = {"dropped": sum(d.count for d in dropped)} | {
        f"dropped on {d.entity}": f"{d.count}, the last {d.last}" for d in dropped
    }
    return _status(level, f"{node}: input", message, node, values)


def _commands_status(node: str, unknown: list[str], refusal: str | None) -> dict[str, Any]:
    named = ", ".join(f"'{name}'" for name in unknown)
    said = [f"commands name unknown joints: {named}"] if unknown else []
    if refusal is not None:
        said.append(f"a message naming no joint of this gateway refused: {refusal}")
    level, message = (WARN, "; ".join(said)) if said else (OK, "ok")
    values = {"unknown_joints": named, "last_refusal": refusal or ""}
    return _status(level, f"{node}: commands", message, node, values)


def _joint_status(node: str, health: JointHealth) -> dict[str, Any]:
    state = health.state or {}
    faults = state.get("faults") or []
    level, message = _joint_level(health, state, faults)
    values = {
        "device": health.device,
        "online": state.get("online", False),
        "stale": state.get("stale", True),
        "faults": ", ".join(faults),
        "estopped": state.get("estopped", False),
        "claimed_by": health.claimed_by or "",
        "last_refusal": health.refusal or "",
    }
    return _status(level, f"{node}: joint {health.joint}", message, health.hardware_id, values)


def _joint_level(health: JointHealth, state: dict[str, Any], faults: list[str]) -> tuple[int, str]:
    if health.state is None:
        return STALE, "no reading"
    if not state.get("online"):
        return ERROR, "offline"
    if state.get("estopped"):
        return ERROR, "e-stopped"
    if faults:
        return ERROR, f"faults: {', '.join(faults)}"
    if state.get("stale"):
        return STALE, "reading stale"
    if health.refusal is not None:
        return WARN, f"command refused: {health.refusal}"
    return OK, "ok"


def _bus_status(node: str, health: BusHealth) -> dict[str, Any]:
    if not health.up:
        level, message = ERROR, "down"
    elif health.new_errors:
        level, message = WARN, f"{health.new_errors} timeouts or bad checksums in the last second"
    else:
        level, message = OK, "up"
    values = {"up": health.up} | {k: v for k, v in health.stats.items() if v is not None}
    return _status(level, f"{node}: bus {health.bus}", message, health.bus, values)


def _status(
    level: int, name: str, message: str, hardware_id: str, values: dict[str, Any]
) -> dict[str, Any]:
    return {
        "level": level,
        "name": name,
        "message": message,
        "hardware_id": hardware_id,
        "values": [{"key": key, "value": _text(value)} for key, value in values.items()],
    }


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
