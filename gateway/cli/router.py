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
   (no polling), then closes the session and exits 0. The close is waited for
   ``CLOSE_WAIT_S`` at most (one line on stderr if it takes longer): zenoh's waits for a
   connect under way, to a router that took the connection and never answers, for up to
   10 s, all of the time systemd's stop gives the unit.
"""

from __future__ import annotations

import argparse
import sys
import threading
from importlib import metadata

import zenoh

from busgate.errors import CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.schemas.endpoints import clash_at
from busgate.schemas.zenoh_session import (
    CLOSE_WAIT_S,
    clean,
    close_within,
    config_file_refusal,
    endpoint_problem,
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
        type=named_path,
        metavar="FILE",
        help="a zenoh config file (.json5, .json, .yaml or .toml: TLS, passwords, access "
        "control …) laid underneath; its mode is set to router, multicast scouting and shared "
        "memory off",
    )
    router.set_defaults(handler=run_router)


def run_router(args: argparse.Namespace) -> int:
    listen: list[str] = args.listen
    for index, endpoint in enumerate(listen):
        if problem := endpoint_problem(endpoint, listening=True):
            raise CommandError(f"--listen {endpoint!r}: {problem}")
        if clash := clash_at(listen, index):
            other, endpoint = clash
            if other == endpoint:
                raise CommandError(f"--listen {endpoint} is given twice")
            raise CommandError(f"--listen {other} and --listen {endpoint} take the same port")
    if args.config is not None and (refusal := config_file_refusal(args.config)):
        raise CommandError(f"--config {args.config}: {refusal}")
    try:
        config = session_config(mode="router", listen=listen, config_file=args.config)
    except zenoh.ZError as exc:  # checked above: only what a race or zenoh itself adds
        raise CommandError(f"cannot build the zenoh config: {clean(zenoh_reason(exc))}") from exc
    except ValueError as exc:  # a Unix socket zenoh would take over
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
                refusal = f"zenoh cannot listen on {where}: {clean(zenoh_reason(exc))}"
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
            if not close_within(session):
                print(
                    f"busgate router: the session did not close within {CLOSE_WAIT_S:g} s (a "
                    "connect under way to an endpoint that does not answer): ending without it",
                    file=sys.stderr,
                )
    return 0
