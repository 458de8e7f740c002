"""``busgate run --config FILE``: the daemon.

It loads and checks the config (refusing it with the same messages as ``check-config``),
starts one bus runner per bus, opens the zenoh session and serves until SIGTERM or SIGINT.
Then it stops in order, within about a second: the streams and the devices (each bus puts its
devices in their safe state and closes, all buses at once), and the zenoh session last.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import logging
import signal
import threading

from busgate.gateway.api import GatewayApi
from busgate.gateway.assembly import build_bus
from busgate.gateway.clock import now, tune_interpreter
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.config import Config, load_config

log = logging.getLogger("busgate")

STOP_TIMEOUT_S = 0.8


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    run = subparsers.add_parser(
        "run",
        help="run the gateway daemon",
        description="Run the gateway: own the configured buses and serve them over zenoh until "
        "SIGTERM or SIGINT.",
    )
    run.add_argument("--config", required=True, help="the gateway's TOML config file")
    run.add_argument("--log-level", default="info", choices=("debug", "info", "warning"))
    run.set_defaults(handler=run_daemon)


def run_daemon(args: argparse.Namespace) -> int:
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    config = load_config(args.config)
    asyncio.run(serve(config))
    return 0


async def serve(config: Config, *, ready: threading.Event | None = None,
                stop: asyncio.Event | None = None) -> None:
    """Serve ``config`` until ``stop`` is set (or SIGTERM/SIGINT when no ``stop`` is given)."""
    from busgate.gateway.bridge import ZenohBridge  # the one module that needs zenoh

    tune_interpreter()
    loop = asyncio.get_running_loop()
    stop = stop or _stop_on_signals(loop)
    bridge: ZenohBridge | None = None
    runners: dict[str, BusRunner] = {}
    try:
        events_sink = []  # events raised before the bridge exists (none expected)
        for bus in config.buses:
            runners[bus.name] = build_bus(bus, on_event=lambda e: _sink(bridge, events_sink, e))
        api = GatewayApi(config.gateway.name, runners, clock=now,
                         on_event=lambda e: _sink(bridge, events_sink, e))
        bridge = ZenohBridge(config, api, runners)
        for runner in runners.values():
            runner.start()
        bridge.open(loop)
        gc.freeze()  # what start-up made lives for good: keep it out of every collection
        log.info("gateway %s serving %d bus(es)", config.gateway.name, len(runners))
        if ready is not None:
            ready.set()
        await bridge.publish_forever(stop)
    finally:
        await asyncio.to_thread(_stop_buses, runners)
        if bridge is not None:
            bridge.publish_events()
            bridge.close()
        log.info("gateway %s stopped", config.gateway.name)


def _sink(bridge, early: list, event) -> None:
    (bridge.events if bridge is not None else early).append(event)


def _stop_buses(runners: dict[str, BusRunner]) -> None:
    """Stop every bus at once: streams, safe state, close."""
    threads = [threading.Thread(target=runner.stop, args=(STOP_TIMEOUT_S,))
               for runner in runners.values()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()


def _stop_on_signals(loop: asyncio.AbstractEventLoop) -> asyncio.Event:
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    return stop
