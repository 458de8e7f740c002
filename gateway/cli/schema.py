"""``busgate schema``: the JSON Schemas of the public data (``busgate.schemas.exported``),
written to ``schemas/json/``.

Rules: the files are generated, never edited by hand, and compare as text, so that
``--check`` (and the test suite) finds one that is out of date. ``--check`` writes nothing;
it exits 1 naming every file that is missing, different, or no longer generated. A file no
longer generated is removed from the repository's folder only: another ``--out`` may hold
JSON files of its owner's (a project's ``package.json``), which are left as they are.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from busgate.errors import CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.schemas import api
from busgate.schemas.exported import SCHEMAS, generated
from busgate.schemas.files import FileRefused, make_folder

#: The repository's ``schemas/json`` (beside the models), whatever the working directory.
DEFAULT_OUT = Path(api.__file__).resolve().parent / "json"


def stale_files(out: Path) -> list[str]:
    """Names of the files in ``out`` that are missing, differ, or (in the repository's folder
    alone) are no longer generated."""
    texts = generated()
    present = {path.name for path in out.glob("*.json")} if out.is_dir() else set()
    stale = [
        name
        for name, text in texts.items()
        if name not in present or (out / name).read_text(encoding="utf-8") != text
    ]
    gone = present - texts.keys() if out.resolve() == DEFAULT_OUT else set()
    return sorted(stale + sorted(gone))


def write_all(out: Path) -> list[str]:
    """Write every schema to ``out`` and remove the ones no longer generated (``stale_files``:
    in the repository's folder alone); return what changed."""
    texts = generated()
    changed = stale_files(out)
    make_folder(out)
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
    try:
        changed = write_all(out)
    except FileRefused as exc:
        raise CommandError(f"--out: {exc}") from exc
    except OSError as exc:
        raise CommandError(f"--out {out}: {exc.strerror or exc}") from exc
    print(
        f"{len(SCHEMAS)} schemas in {out}; {len(changed)} changed"
        + (f": {', '.join(changed)}" if changed else "")
    )
    return 0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "schema",
        description="Write one JSON Schema per message of the API to schemas/json/: each "
        "device kind's commands, follow targets and telemetry; the bus, trajectory and base "
        "commands; replies, events, bus statistics, info, the joints message, a base's twist "
        "and odometry; a recording's frames and commands; and the config.",
    )
    parser.add_argument(
        "--out",
        default=str(DEFAULT_OUT),
        type=named_path,
        help="directory to write to (default: the repository's schemas/json)",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 naming the files that are out of date",
    )
    parser.set_defaults(handler=_run)
