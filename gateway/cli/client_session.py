"""How the client commands (``busgate send``, ``busgate watch``) reach gateways: the options
that pick the session (``--connect``, ``--prefix``, ``--mode``, ``--zenoh-config`` and the
credentials ``--user``, ``--password-file``, ``--ca``) and the ``busgate.client`` they open
with them. ``DEFAULT_ENDPOINT`` is also where ``busgate demo`` listens, so that the commands
find each other without options.

A password is read from a file (or ``BUSGATE_PASSWORD``), never taken on the command line,
where every user of the host could read it in the process list.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

import busgate.client as bc
from busgate.client.core import CLIENT_MODES
from busgate.errors import CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.schemas.files import FileRefused, read_text

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "busgate"
PASSWORD_VARIABLE = "BUSGATE_PASSWORD"
#: The longest password file read: a password is a line (``/dev/zero`` would be read for ever).
MAX_PASSWORD_FILE_BYTES = 4096


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
        choices=CLIENT_MODES,
        default="client",
        help="zenoh mode of this tool's session (default client)",
    )
    parser.add_argument(
        "--zenoh-config",
        default=None,
        type=named_path,
        metavar="FILE",
        help="a zenoh config file (TLS, auth …) laid underneath",
    )
    parser.add_argument("--user", default=None, help="zenoh user name (with --password-file)")
    parser.add_argument(
        "--password-file",
        default=None,
        type=named_path,
        metavar="FILE",
        help=f"a file holding the user's password (default: ${PASSWORD_VARIABLE})",
    )
    parser.add_argument(
        "--ca",
        default=None,
        type=named_path,
        metavar="FILE",
        help="the CA certificate of a tls/ endpoint",
    )


def open_client(args: argparse.Namespace, tool: str) -> bc.Client:
    """A ``busgate.client`` for a command-line tool (``ConnectError``: one line, exit 2, with
    a hint where nobody answered and nothing else is known: the usual case is a gateway not
    started yet)."""
    try:
        return bc.connect(**client_options(args, tool))
    except bc.ConnectError as exc:
        if not exc.unreached:
            raise  # its own words say what a login, a TLS link or a config file may lack
        raise bc.ConnectError(
            f"{exc} (is a gateway listening there? `busgate demo` listens on "
            f"{DEFAULT_ENDPOINT}; --connect names another endpoint)"
        ) from exc


def client_options(args: argparse.Namespace, tool: str) -> dict[str, Any]:
    """What ``bc.connect`` and ``bc.aio.connect`` take, from the options above."""
    return {
        "endpoints": args.connect or [DEFAULT_ENDPOINT],
        "client_id": f"busgate-{tool}-{os.getpid()}",
        "prefix": args.prefix,
        "mode": args.mode,
        "config_file": args.zenoh_config,
        "username": args.user,
        "password": _password(args),
        "ca": args.ca,
    }


def _password(args: argparse.Namespace) -> str | None:
    """The password of ``--user``: its ``--password-file``'s, else the environment's. A file
    without a user, an empty user or an empty file is refused: each failed as a gateway
    nobody answered (an audit)."""
    if args.user is not None and not args.user.strip():
        raise CommandError("--user names an account, not an empty string")
    if args.password_file is None:
        return os.environ.get(PASSWORD_VARIABLE) if args.user is not None else None
    if args.user is None:
        raise CommandError("--password-file needs --user: the account it is the password of")
    try:
        password = read_text(args.password_file, MAX_PASSWORD_FILE_BYTES, "a password file")
    except FileRefused as exc:
        raise CommandError(f"--password-file: {exc}") from exc
    if not password.strip():
        raise CommandError(f"--password-file: {args.password_file} holds no password")
    return password.strip()
