"""``busgate schema``: the JSON Schemas of the public data, written to ``schemas/json/``.

One file per thing a client sends or reads: the commands of each device kind's ``cmd`` key
(its own ops plus ``claim`` / ``release``), the bus ``cmd`` key's ops, the trajectory key's
ops, the replies, each kind's telemetry and follow target, the events, the bus statistics, the
info reply, and the config file.

Rules: the files are generated, never edited by hand, and the output is deterministic (keys
sorted, two-space indent, one trailing newline) so that ``--check`` (and the test suite)
compares text. ``--check`` writes nothing; it exits 1 naming every file that is missing,
different, or no longer generated.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter

from busgate.schemas import api, trajectory
from busgate.schemas.config import Config

DRAFT = "https://json-schema.org/draft/2020-12/schema"
#: The repository's ``schemas/json`` (beside the models), whatever the working directory.
DEFAULT_OUT = Path(api.__file__).resolve().parent / "json"

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
            "target, sent at the device's follow period.",
            model,
        )
        for kind, model in api.FOLLOW_MODELS.items()
    },
    "event.json": (
        "busgate event",
        "What <prefix>/<gw>/dev/<device>/event and <prefix>/<gw>/events carry.",
        api.EVENT_ADAPTER,
    ),
    "bus_stats.json": (
        "busgate bus statistics",
        "What <prefix>/<gw>/bus/<bus>/stats carries, once a second.",
        api.BusStatistics,
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


def stale_files(out: Path) -> list[str]:
    """Names of the files in ``out`` that are missing, differ, or are no longer generated."""
    texts = generated()
    present = {path.name for path in out.glob("*.json")} if out.is_dir() else set()
    stale = [
        name
        for name, text in texts.items()
        if name not in present or (out / name).read_text(encoding="utf-8") != text
    ]
    return sorted(stale + sorted(present - texts.keys()))


def write_all(out: Path) -> list[str]:
    """Write every schema to ``out`` and remove the ones no longer generated; return what
    changed."""
    changed = stale_files(out)
    out.mkdir(parents=True, exist_ok=True)
    texts = generated()
    for name in changed:
        path = out / name
        if name in texts:
            path.write_text(texts[name], encoding="utf-8")
        else:
            path.unlink()
    return changed


def _run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.check:
        stale = stale_files(out)
        for name in stale:
            print(f"stale: {out / name}", file=sys.stderr)
        if stale:
            print("regenerate with: busgate schema", file=sys.stderr)
        return 1 if stale else 0
    changed = write_all(out)
    print(
        f"{len(SCHEMAS)} schemas in {out}; {len(changed)} changed"
        + (f": {', '.join(changed)}" if changed else "")
    )
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "schema",
        description="Write one JSON Schema per command set, reply, telemetry kind, event, bus "
        "statistics, info and config to schemas/json/.",
    )
    parser.add_argument(
        "--out",
        default=str(DEFAULT_OUT),
        help="directory to write to (default: the repository's schemas/json)",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 naming the files that are out of date",
    )
    parser.set_defaults(handler=_run)
