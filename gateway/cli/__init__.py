"""The ``busgate`` command: one parser, subcommands added by the modules that own them.

A ``BusgateError`` (a bad command line, a refused command) is printed as one line and exits
with status 2, never as a traceback. ``busgate --version`` prints the installed version;
``busgate`` alone prints the help, listing the commands, on stderr and exits with status 2 (a
command is missing, as for any other usage error).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from busgate.codecs.errors import BusgateError
from busgate.gateway import installed_version
from busgate.gateway.cli import bench, check_config, client, codec, demo, schema
from busgate.gateway.service import daemon
from busgate.gateway.sim import cli as sim


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="busgate",
        description="busgate: a gateway between motion-device buses (Inspire LA actuators, "
        "ZLAC706 hub-motor drivers, DS serial servos) and Eclipse Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"busgate {installed_version()}")
    subparsers = parser.add_subparsers(dest="subcommand", required=True, metavar="COMMAND")
    for module in (codec, sim, bench, client, daemon, check_config, demo, schema):
        module.add_parsers(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except BusgateError as exc:
        print(f"busgate {args.subcommand}: error: {exc}", file=sys.stderr)
        return 2
