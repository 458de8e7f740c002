"""``busgate dashboard``: the fleet in a browser (``busgate.dashboard``), through one
``busgate.client`` session opened with the client commands' options and credentials.

It listens on 127.0.0.1 unless told otherwise: whoever reaches the page sees every gateway
and may e-stop any, reset its e-stop and enable any device, with the dashboard's zenoh
account (docs/fleet.md, "Who may do what").
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import TYPE_CHECKING

from busgate.client import aio
from busgate.gateway.cli.client_session import add_session_options, client_options
from busgate.gateway.service.daemon import stop_on_signals

if TYPE_CHECKING:
    from busgate.dashboard.server import Listen


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    from busgate.dashboard.server import DEFAULT_LISTEN

    dashboard = subparsers.add_parser(
        "dashboard",
        description="Serve a live web page of every gateway on the zenoh network: devices, "
        "plots, events, an e-stop per gateway and for the fleet, an enable per device.",
    )
    add_session_options(dashboard)
    dashboard.add_argument(
        "--listen",
        default=DEFAULT_LISTEN,
        metavar="HOST:PORT",
        help=f"where the page is served (default {DEFAULT_LISTEN}; port 0: any free one)",
    )
    dashboard.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name (or address) a browser may reach the page by, besides the listen "
        "address's own: the robot's DNS name, a proxy's (repeatable)",
    )
    dashboard.set_defaults(handler=run_dashboard)


async def _connected(args: argparse.Namespace) -> aio.Client:
    return await aio.connect(**client_options(args, "dashboard"))


def run_dashboard(args: argparse.Namespace) -> int:
    from busgate.dashboard.server import Listen

    listen = Listen.parse(args.listen, args.allow_host)  # refused before any session opens
    if (exposed := listen.exposure()) is not None:
        print(f"busgate dashboard: warning: {exposed}", file=sys.stderr)
    asyncio.run(_serve(args, listen))
    return 0


async def _serve(args: argparse.Namespace, listen: Listen) -> None:
    from busgate.dashboard.server import serve_dashboard

    stop = stop_on_signals(asyncio.get_running_loop())
    connecting = asyncio.ensure_future(_connected(args))
    stopped = asyncio.ensure_future(stop.wait())
    await asyncio.wait((connecting, stopped), return_when=asyncio.FIRST_COMPLETED)
    stopped.cancel()
    if not connecting.done():  # a stop while zenoh waits (10 s for an endpoint that never
        connecting.cancel()  # answers): heard at once, as the gateway hears it
        print("busgate dashboard: stopped before a session opened", file=sys.stderr)
        return
    client = connecting.result()
    try:
        await serve_dashboard(
            client,
            listen,
            stop,
            prefix=args.prefix,
            on_ready=lambda url: print(f"busgate dashboard: serving {url}", flush=True),
        )
    finally:
        await client.close()
