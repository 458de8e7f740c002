"""What spans the devices of one bus: group moves that start together, and scans.

A bus-level ``group_move`` names devices; here it becomes the device kind's own group op (one
0xF2 broadcast frame for Inspire LA actuators, one SYNC WRITE for DS servos; each driver's
``group_entry`` says its part, or that its kind has none), validated by that kind's schema,
so the devices start in the same frame. A ``scan`` sends each id the most harmless frame its
protocol answers (each driver's ``probe``: LA status query, DS ping, a ZLAC706 CAN write to a
register the node does not have, the RS232 monitor), once: a silent id costs one reply
window, so a full scan stays short (retried probes and the hold-offs after their timeouts made
one of three actuators take ten seconds).
"""

from __future__ import annotations

import json
from typing import Any

from busgate.errors import RefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.families import driver_class
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.families import PROTOCOLS


def group_command(runner: BusRunner, request) -> tuple[str, Any]:
    """The device-level group op that moves ``request.targets`` together, and the device
    whose driver carries it."""
    drivers = [runner.drivers[target.device] for target in request.targets]
    targets = [
        driver.group_entry(target.position, target.time_ms)
        for target, driver in zip(request.targets, drivers, strict=True)
    ]
    first = drivers[0]
    command = {"op": "group_move", "targets": targets, "require_claim": request.require_claim}
    return first.name, first.parse(json.dumps(command))


def scan_ids(protocol: str) -> range:
    """The ids a scan of a ``protocol`` bus probes by default: every id the protocol allows
    (one probe on a line whose frames carry no id)."""
    entry = PROTOCOLS[protocol]
    ids = entry.device_ids
    return ids if entry.addressed else ids[:1]


def scan_requests(protocol: str, ids: list[int] | None) -> list[Request]:
    """One probe per id (default: every id the protocol allows); ``out_of_range`` for an id
    the protocol does not have."""
    allowed, probe = scan_ids(protocol), driver_class(PROTOCOLS[protocol]).probe
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
