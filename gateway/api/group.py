"""What spans the devices of one bus: group moves that start together, and scans.

A bus-level ``group_move`` names devices; here it becomes the device kind's own group op (one
0xF2 broadcast frame for Inspire LA actuators, one SYNC WRITE for DS servos), validated by that
kind's schema, so the devices start in the same frame. A ``scan`` sends each id the most
harmless frame its protocol answers (LA: status query; DS: ping; ZLAC706 CAN: a write to a
register the driver does not have, answered ``FF`` and changing nothing; RS232: the monitor),
once: a silent id costs one reply window, so a full scan stays short (retried probes and the
hold-offs after their timeouts made one of three actuators take ten seconds).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.errors import CommandError, RefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.scheduler.runner import BusRunner

#: A CAN register the ZLAC706 does not have: writing it gets the "no such register" reply.
_ZLAC_PROBE_REGISTER = 0x7E


class GroupError(CommandError):
    """A group move the bus's devices cannot make."""


def _la_target(target, driver) -> dict[str, Any]:
    if target.time_ms is not None:
        raise GroupError("Inspire LA group moves have no move time; drop time_ms")
    return {"id": driver.device_id, "position": target.position}


def _ds_target(target, driver) -> dict[str, Any]:
    return {"id": driver.device_id, "position": target.position, "time_ms": target.time_ms or 0}


_GROUP_TARGETS: dict[str, Callable[[Any, Any], dict[str, Any]]] = {
    "inspire_la": _la_target,
    "ds_servo": _ds_target,
}


def group_command(runner: BusRunner, request) -> tuple[str, Any]:
    """The device-level group op that moves ``request.targets`` together, and the device
    whose driver carries it."""
    make = _GROUP_TARGETS.get(runner.timing.protocol)
    if make is None:
        raise GroupError(f"a {runner.timing.protocol} bus has no group move")
    drivers = [runner.drivers[target.device] for target in request.targets]
    targets = [
        make(target, driver) for target, driver in zip(request.targets, drivers, strict=True)
    ]
    first = drivers[0]
    return first.name, first.parse(json.dumps({"op": "group_move", "targets": targets}))


_PROBES: dict[str, tuple[range, Callable[[int], Request]]] = {
    "inspire_la": (
        range(1, 255),
        lambda i: Request.of(
            inspire_la, inspire_la.ControlCommand(i, inspire_la.ControlCode.STATUS)
        ),
    ),
    "ds_servo": (range(1, 251), lambda i: Request.of(ds_servo, ds_servo.Ping(i))),
    "zlac706_can": (
        range(1, 110),
        lambda i: Request.of(zlac706_can, zlac706_can.Write(i, _ZLAC_PROBE_REGISTER, 0)),
    ),
    "zlac706_rs232": (
        range(0, 1),
        lambda i: Request.of(zlac706_rs232, zlac706_rs232.MonitorRequest()),
    ),
}


def scan_requests(protocol: str, ids: list[int] | None) -> list[Request]:
    """One probe per id (default: every id the protocol allows); ``out_of_range`` for an id
    the protocol does not have."""
    allowed, probe = _PROBES[protocol]
    outside = [i for i in ids or () if i not in allowed]
    if outside:
        raise RefusedError(
            "out_of_range",
            f"ids on a {protocol} bus are {allowed.start}-"
            f"{allowed.stop - 1}, not {', '.join(map(str, outside))}",
        )
    return [probe(i) for i in (allowed if ids is None else ids)]


def scan_result(protocol: str, outcomes: list[tuple[Request, tuple | None]]) -> list[dict]:
    """The ids that answered, and as what (the reply's frame type)."""
    found = []
    for request, reply in outcomes:
        if reply:
            source = request.expected.source_id if request.expected else None
            found.append({"id": source, "protocol": protocol, "reply": type(reply[0]).__name__})
    return found
