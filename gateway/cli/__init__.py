"""The ``busgate`` command: one parser, subcommands added by the modules that own them.

A ``BusgateError`` (a bad command line, a refused command) is printed as one line and exits
with status 2, never as a traceback; one that names several problems (a config refused by
``busgate run``) is printed one line each, every line with the command's prefix. A Ctrl-C
that the command does not take for its own stop (``send`` waiting for a session or a reply)
is one line too, exit status 130 (``INTERRUPTED``, as a shell reports a command Ctrl-C
ended). ``busgate --version`` prints the installed version; ``busgate`` alone prints the
help, listing the commands, on stderr and exits with status 2 (a command is missing, as for
any other usage error).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys
from collections.abc import Sequence

from busgate.errors import BusgateError
from busgate.gateway import installed_version

#: The exit status of a command a Ctrl-C ended (128 + SIGINT).
INTERRUPTED = 130
#: The errors of a write that found no room (stdout ``> /dev/full``, a full disk): told in one
#: line, as a refusal is, where any other is a bug's (an EIO may be a device's: told whole).
WRITE_FAILURES = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
#: Each command, the module that adds its parser and carries it out, and its line in the
#: list. A module is imported only for its own command: ``busgate --help`` and ``busgate
#: encode`` load no zenoh, pyserial, python-can or prometheus_client.
COMMANDS: dict[str, tuple[str, str]] = {
    "encode": ("busgate.gateway.cli.codec", "print the frames that carry out a JSON command"),
    "decode": ("busgate.gateway.cli.codec", "decode frames from hex"),
    "sim": ("busgate.gateway.sim.cli", "serve simulated devices on a new pty"),
    "bench": (
        "busgate.gateway.cli.bench",
        "measure the bus owner and scheduler against a port or the simulators",
    ),
    "send": ("busgate.gateway.cli.client", "send a JSON command to a device and print the reply"),
    "watch": ("busgate.gateway.cli.client", "a live table of device states and bus statistics"),
    "run": ("busgate.gateway.service.daemon", "run the gateway daemon"),
    "check-config": (
        "busgate.gateway.cli.check_config",
        "validate a config and print each bus's budget",
    ),
    "dashboard": (
        "busgate.gateway.cli.dashboard",
        "serve a live web page of every gateway: devices, plots, events, e-stop",
    ),
    "demo": ("busgate.gateway.cli.demo", "run the gateway on simulated devices of every kind"),
    "record": (
        "busgate.gateway.cli.record",
        "record the fleet's telemetry to an MCAP file (--info: what a file holds)",
    ),
    "replay": ("busgate.gateway.cli.replay", "publish a recording's telemetry again"),
    "router": (
        "busgate.gateway.cli.router",
        "run a zenoh router for many gateways (where zenohd is not installed)",
    ),
    "schema": (
        "busgate.gateway.cli.schema",
        "write the JSON Schemas of commands, replies, telemetry, events and config",
    ),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser, with ``command``'s own arguments (the others are listed by name only)."""
    parser = argparse.ArgumentParser(
        prog="busgate",
        description="busgate: a gateway between motion-device buses (Inspire LA actuators, "
        "ZLAC706 hub-motor drivers, DS serial servos) and Eclipse Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"busgate {installed_version()}")
    subparsers = parser.add_subparsers(dest="subcommand", required=True, metavar="COMMAND")
    chosen = COMMANDS[command][0] if command in COMMANDS else None
    if chosen is not None:
        importlib.import_module(chosen).add_parsers(subparsers)
    for name, (module, line) in COMMANDS.items():
        if module != chosen:
            subparsers.add_parser(name, help=line)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((arg for arg in argv if not arg.startswith("-")), None)
    try:  # a Ctrl-C while the command's module loads (zenoh, pydantic: some 0.5 s) too
        parser = build_parser(command)
    except KeyboardInterrupt:
        return _interrupted(command or "")
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except BusgateError as exc:
        for line in str(exc).splitlines() or [type(exc).__name__]:
            print(f"busgate {args.subcommand}: error: {line}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # stdout's reader left (| head): nothing more to say, to anyone
        _drop_stdout()
        return 1
    except OSError as exc:
        if exc.errno not in WRITE_FAILURES:
            raise  # no output that could not be written: a bug, told whole
        _drop_stdout()  # what waits in it would fail again at the exit's flush
        print(f"busgate {args.subcommand}: error: cannot write its output: {exc.strerror}",
              file=sys.stderr)  # fmt: skip
        return 1
    except KeyboardInterrupt:  # a Ctrl-C that no command took for its own stop
        return _interrupted(args.subcommand)


def _drop_stdout() -> None:
    """Whatever is written to stdout from now on, and what waits in it, goes nowhere."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _interrupted(command: str) -> int:
    print(f"busgate {command}: stopped (Ctrl-C)" if command else "busgate: stopped (Ctrl-C)",
          file=sys.stderr)  # fmt: skip
    return INTERRUPTED
