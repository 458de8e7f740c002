"""How ``busgate send`` and ``busgate watch`` reach gateways over zenoh: the options that pick
the session (``--connect``, ``--prefix``, ``--mode``, ``--zenoh-config``), the session they
open, and key expressions checked before zenoh sees them. ``DEFAULT_ENDPOINT`` is also where
``busgate demo`` listens, so that the two commands find each other without options.

Apart from ``client.py`` (what the commands do) so that each command stands on one way in; it
imports ``zenoh``, and its settings come from ``gateway/api/zenoh_config.py``, which the
daemon's side uses too.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from busgate.client.errors import ConnectError
from busgate.client.zenoh_config import session_config, zenoh_reason
from busgate.codecs.errors import CommandError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "busgate"


def add_session_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        default=None,
        help=f"zenoh endpoint, repeatable (default {DEFAULT_ENDPOINT})",
    )
    parser.add_argument(
        "--prefix",
        default=DEFAULT_PREFIX,
        help=f"the gateways' key prefix (default {DEFAULT_PREFIX})",
    )
    parser.add_argument(
        "--mode",
        choices=("client", "peer"),
        default="client",
        help="zenoh mode of this tool's session (default client)",
    )
    parser.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a zenoh config file (TLS, auth …) laid underneath",
    )


#: zenoh carries a message in batches of 64 KiB; a longer key makes the client session panic.
MAX_KEY_BYTES = 60 * 1024


def key_expr(text: str) -> zenoh.KeyExpr:
    """``text`` as a key expression; ``CommandError`` (one line, exit 2) when zenoh would
    refuse it or it is too long to send."""
    if len(text.encode()) > MAX_KEY_BYTES:
        raise CommandError(
            f"a key expression of {len(text.encode())} bytes: at most "
            f"{MAX_KEY_BYTES} fit in a zenoh message"
        )
    try:
        return zenoh.KeyExpr(text)
    except zenoh.ZError as exc:
        raise CommandError(f"not a key expression: {text[:200]!r} ({zenoh_reason(exc)})") from exc


@contextmanager
def client_session(args: argparse.Namespace) -> Iterator[zenoh.Session]:
    """A zenoh session for a client tool: ``--connect``, multicast scouting off; closed after."""
    endpoints = args.connect or [DEFAULT_ENDPOINT]
    try:
        config = session_config(
            mode=args.mode,
            connect=endpoints,
            multicast_scouting=False,
            config_file=args.zenoh_config,
        )
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise ConnectError(
            f"cannot open a zenoh session to {', '.join(endpoints)}: {zenoh_reason(exc)}"
        ) from exc
    try:
        yield session
    finally:
        session.close()
