"""``busgate router``: a zenoh router from the Python binding, for hosts where zenohd is not
installed (zenohd remains the recommended router where it is). A fleet's gateways and
clients meet in it: each joins with ``mode = "client"`` and ``connect`` to its endpoint.

Rules of this file:

1. It is zenoh's own router, nothing of busgate's: ``zenoh.open`` in router mode, with no key,
   queryable or access rule of its own. What a site needs beyond endpoints (TLS, passwords,
   access control) comes from a zenoh config file (``--config``), laid underneath.
2. It listens only where it is told: ``--listen`` is required (no default that opens a port
   nobody asked for) and replaces the file's listen endpoints. Multicast scouting is off
   (``session_config``): busgate's sessions meet at explicit endpoints, never whoever
   answers on the LAN. So is zenoh's shared memory, whatever the file says (``session_config``).
3. Every refusal comes before anything serves and is one line with exit status 2 (a
   ``CommandError``): a malformed endpoint, a config file missing, not a file or malformed,
   an endpoint zenoh cannot listen on (in use, a bad port or host). zenoh's reason is kept,
   cleaned of the Rust source locations and debug wrappers it carries.
4. One line on stdout once the router serves, flushed (for a terminal, journald, or a
   test waiting for it); nothing after it. zenoh's own log stays off unless ``RUST_LOG``
   asks for it.
5. It serves until SIGTERM or SIGINT (Ctrl-C), waiting on an event the signal handlers set
   (no polling), then closes the session and exits 0.
"""

from __future__ import annotations

import argparse
import json
import re
import threading
from importlib import metadata
from pathlib import Path

import zenoh

from busgate.errors import CommandError
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.schemas.zenoh_session import (
    config_file_problem,
    session_config,
    session_refusal,
    zenoh_reason,
)

IN_USE_HINT = "another busgate router, zenohd or gateway?"


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    router = subparsers.add_parser(
        "router",
        description="Run a zenoh router (zenoh's Python binding, in router mode) that "
        'gateways and clients join with mode = "client" and connect = [ENDPOINT]. '
        "zenohd is the recommended router where it is installed; this one is for hosts "
        "without it. Multicast scouting is off: busgate's sessions meet at explicit "
        "endpoints. Serves until SIGTERM or Ctrl-C.",
        epilog="zenoh's own log is off; RUST_LOG=info (or debug) turns it on, on stdout.",
    )
    router.add_argument(
        "--listen",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447; repeatable, required "
        "(it replaces the config file's listen endpoints)",
    )
    router.add_argument(
        "--config",
        default=None,
        metavar="FILE",
        help="a zenoh config file (.json5, .json, .yaml or .toml: TLS, passwords, access "
        "control …) laid underneath; its mode is set to router, multicast scouting and shared "
        "memory off",
    )
    router.set_defaults(handler=run_router)


def run_router(args: argparse.Namespace) -> int:
    listen: list[str] = args.listen
    for endpoint in listen:
        _check_endpoint(endpoint)
        if listen.count(endpoint) > 1:  # zenoh would say it is in use: by itself
            raise CommandError(f"--listen {endpoint} is given twice")
    if args.config is not None:
        _check_config_file(Path(args.config))
    try:
        config = session_config(mode="router", listen=listen, config_file=args.config)
    except zenoh.ZError as exc:  # checked above: only what a race or zenoh itself adds
        raise CommandError(f"cannot build the zenoh config: {_clean(zenoh_reason(exc))}") from exc
    except ValueError as exc:  # no zenoh config file, a Unix socket zenoh would take over
        raise CommandError(str(exc)) from exc
    zenoh.try_init_log_from_env()
    stop = threading.Event()
    with stopped_by_signals(stop):
        try:
            session = zenoh.open(config)
        except zenoh.ZError as exc:
            refusal = session_refusal(exc, IN_USE_HINT)
            if refusal.startswith("cannot open the zenoh session: "):  # not an endpoint in use
                where = ", ".join(listen)
                refusal = f"zenoh cannot listen on {where}: {_clean(zenoh_reason(exc))}"
            raise CommandError(refusal) from exc
        try:
            version = metadata.version("eclipse-zenoh")
            print(
                f"busgate router: serving on {', '.join(listen)} "
                f"(zenoh {version}, id {session.info.zid()})",
                flush=True,
            )
            stop.wait()
        finally:
            session.close()
    return 0


def _check_endpoint(endpoint: str) -> None:
    """Refuse an endpoint zenoh cannot parse, naming it (what parses but cannot be listened
    on, a bad port or host, is zenoh.open's to refuse)."""
    try:
        zenoh.Config().insert_json5("listen/endpoints", json.dumps([endpoint]))
    except zenoh.ZError as exc:
        raise CommandError(f"--listen {endpoint!r}: {_clean(zenoh_reason(exc))}") from exc


def _check_config_file(path: Path) -> None:
    """Refuse a ``--config`` that is missing, not a file, unreadable or not a zenoh config."""
    problem = config_file_problem(path)
    if problem is not None:
        raise CommandError(f"--config {path}: {problem}")
    try:
        zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise CommandError(f"--config {path}: {_config_file_reason(exc)}") from exc


_PARSER_POSITION = re.compile(r"^\s*--> (?P<line>\d+):(?P<column>\d+)")
_PARSER_EXPECTED = re.compile(r"^\s*= (?P<msg>.+)$", re.M)
#: The Rust debug prints zenoh wraps a config file's refusal in (serde_json/json5, YAML, TOML).
_DEBUG_PRINTS = (
    re.compile(
        r'msg: "(?P<msg>.*?)",\s*location: Some\(Location \{ line: (?P<line>\d+), '
        r"column: (?P<column>\d+) \}\)"
    ),
    re.compile(r'Error\("(?P<msg>.*)", line: (?P<line>\d+), column: (?P<column>\d+)\)'),
    re.compile(r'message: "(?P<msg>.*?)", input: '),
)


def _config_file_reason(exc: BaseException) -> str:
    """zenoh's reason for refusing a config file, on one line: where in the file when zenoh
    says (its json5 parser draws a caret diagram over several lines, serde a Rust debug
    print), and what is wrong there (tests/test_router.py has each form, from zenoh itself)."""
    text = str(exc)
    position, expected = _PARSER_POSITION.match(text), _PARSER_EXPECTED.search(text)
    if position is not None and expected is not None:  # json5's parser: a caret diagram
        reason = zenoh_reason(Exception(expected.group("msg")))
        return f"line {position['line']}, column {position['column']}: {reason}"
    reason = zenoh_reason(exc)
    for debug_print in _DEBUG_PRINTS:
        found = debug_print.search(reason)
        if found is not None:
            where = found.groupdict().get("line")
            at = f"line {where}, column {found['column']}: " if where is not None else ""
            return at + found["msg"]
    return reason


def _clean(reason: str) -> str:
    """``reason`` without the Rust debug print around its message, when it has one."""
    found = re.search(r'msg: "(.*?)"(?:,\s*location|\s*\})', reason)
    return found.group(1) if found is not None else reason
