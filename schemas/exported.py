"""The JSON Schemas of busgate's public data, made from the models: one per thing a client
sends or reads (each device kind's commands, the bus and trajectory commands, the replies,
each kind's telemetry and follow target, the events, the bus statistics, the info reply), the
config file, and what only an incident file holds (a bus's frames, the commands). ``busgate
schema`` writes them to ``schemas/json/``; a recording names them for its channels
(``busgate.gateway.recording``).

Rules: the text of a schema is deterministic (keys sorted, two-space indent, one trailing
newline), so the files compare as text.
"""

from __future__ import annotations

import json
from typing import Any

from pydantic import TypeAdapter

from busgate.schemas import api, bases, events, recording, trajectory
from busgate.schemas.config import Config

DRAFT = "https://json-schema.org/draft/2020-12/schema"
#: File name → (title, what it describes, the type whose schema it holds).
SCHEMAS: dict[str, tuple[str, str, Any]] = {
    **{
        f"command.{kind}.json": (
            f"busgate {kind} command",
            f"A JSON command for <prefix>/<gw>/dev/<device>/cmd on a {kind} device: the kind's "
            "own ops and the gateway's claim and release.",
            adapter,
        )
        for kind, adapter in api.DEVICE_COMMAND_ADAPTERS.items()
    },
    "command.bus.json": (
        "busgate bus command",
        "A JSON command for <prefix>/<gw>/bus/<bus>/cmd: group_move or scan.",
        api.BUS_COMMAND_ADAPTER,
    ),
    "command.trajectory.json": (
        "busgate trajectory command",
        "A JSON command for <prefix>/<gw>/trajectory: play a trajectory on several devices, "
        "cancel one, or ask what is playing.",
        trajectory.TRAJECTORY_COMMAND_ADAPTER,
    ),
    "reply.json": (
        "busgate reply",
        'The answer of a cmd queryable: {"ok": true, ...} or {"ok": false, "error": {"code", '
        '"message"}}.',
        api.REPLY_ADAPTER,
    ),
    **{
        f"telemetry.{kind}.json": (
            f"busgate {kind} telemetry",
            f"What <prefix>/<gw>/dev/<device>/state carries for a {kind} device.",
            model,
        )
        for kind, model in api.TELEMETRY_MODELS.items()
    },
    **{
        f"follow.{kind}.json": (
            f"busgate {kind} follow target",
            f"What <prefix>/<gw>/dev/<device>/follow takes for a {kind} device: the latest "
            "target (the kind's own, or the joint's in SI), sent at the device's follow period.",
            model | api.JointFollow,
        )
        for kind, model in api.FOLLOW_MODELS.items()
    },
    "joints.json": (
        "busgate joints",
        "What <prefix>/<gw>/joints carries: every joint of the gateway in SI units.",
        api.JointsMessage,
    ),
    "odometry.json": (
        "busgate base odometry",
        "What <prefix>/<gw>/base/<name>/odom carries: the base's pose from its wheels' "
        "encoders, its measured and commanded twist.",
        bases.Odometry,
    ),
    "base_command.json": (
        "busgate base command",
        "What <prefix>/<gw>/base/<name>/cmd takes: twist, stop, claim, release, enable, "
        "disable, reset_odometry, status.",
        bases.BASE_COMMAND_ADAPTER,
    ),
    "twist.json": (
        "busgate base twist",
        "What <prefix>/<gw>/base/<name>/twist takes: the latest twist of a stream.",
        bases.TwistTarget,
    ),
    "event.json": (
        "busgate event",
        "What <prefix>/<gw>/dev/<device>/event and <prefix>/<gw>/events carry.",
        events.EVENT_ADAPTER,
    ),
    "bus_stats.json": (
        "busgate bus statistics",
        "What <prefix>/<gw>/bus/<bus>/stats carries, once a second.",
        api.BusStatistics,
    ),
    "frame.json": (
        "busgate recorded frame",
        "What <prefix>/<gw>/bus/<bus>/frames holds in an incident file: one frame or read on "
        "the bus.",
        recording.RecordedFrame,
    ),
    "recorded_command.json": (
        "busgate recorded command",
        "What <prefix>/<gw>/commands holds in an incident file: a command and its answer.",
        recording.RecordedCommand,
    ),
    "info.json": (
        "busgate info",
        "The answer of the <prefix>/<gw>/info queryable.",
        api.InfoReply,
    ),
    "config.json": (
        "busgate config",
        "The gateway's configuration file (TOML), as parsed.",
        Config,
    ),
}


def schema_of(title: str, description: str, target: Any) -> dict[str, Any]:
    """The JSON Schema of a model or a ``TypeAdapter``, with its title and dialect."""
    adapter = target if isinstance(target, TypeAdapter) else TypeAdapter(target)
    schema = adapter.json_schema()
    return {"$schema": DRAFT, **schema, "title": title, "description": description}


def render(schema: dict[str, Any]) -> str:
    """The file text: the same schema always gives the same bytes."""
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def generated() -> dict[str, str]:
    """File name → text, for every schema."""
    return {name: render(schema_of(*entry)) for name, entry in SCHEMAS.items()}
