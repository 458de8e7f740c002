"""``busgate run --config FILE``: the daemon.

It loads and checks the config (refusing it with the same messages as ``check-config``),
starts one bus runner per bus, opens the zenoh session and serves until SIGTERM or SIGINT.
Under systemd (Type=notify) it says READY once every bus is open, pings the watchdog only
while every bus thread keeps its schedule, and says STOPPING on the way out.
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
from collections import deque

from busgate.gateway.api import GatewayApi
from busgate.gateway.assembly import build_bus
from busgate.gateway.budget import bus_budget
from busgate.gateway.clock import now, tune_interpreter
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.metrics import Metrics
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.sdnotify import Notifier, Watchdog
from busgate.schemas.config import Config, load_config

log = logging.getLogger("busgate")

STOP_TIMEOUT_S = 0.8
BUS_OPEN_POLL_S = 0.01
EVENT_BACKLOG = 10_000
#: New device states waiting for the publisher: two seconds of 20 devices at 100 Hz.
STATE_BACKLOG = 4_096


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
    notifier = Notifier()
    events: deque[DeviceEvent] = deque(maxlen=EVENT_BACKLOG)
    states: deque[tuple[str, dict]] = deque(maxlen=STATE_BACKLOG)
    runners = {
        bus.name: build_bus(bus, on_event=events.append,
                            on_state=lambda device, state: states.append((device, state)))
        for bus in config.buses
    }
    api = GatewayApi(config.gateway.name, runners, clock=now, on_event=events.append)
    bridge = ZenohBridge(config, api, runners, events, states)
    metrics: Metrics | None = None
    try:
        _log_budgets(config)
        for runner in runners.values():
            runner.start()
        bridge.open(loop)
        if config.metrics is not None:
            metrics = Metrics(runners, clients=bridge.connections).start(config.metrics.listen)
            bridge.on_latency = metrics.observe
            log.info("metrics on http://%s/metrics", config.metrics.listen)
        gc.freeze()  # what start-up made lives for good: keep it out of every collection
        log.info("gateway %s serving %d bus(es)", config.gateway.name, len(runners))
        if ready is not None:
            ready.set()
        watchdog = Watchdog(notifier, lambda: all(r.keeping_schedule() for r in runners.values()))
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(_ready_when_open(notifier, config, runners, stop))
            tasks.create_task(watchdog.run(stop))
            await bridge.publish_forever(stop)
    finally:
        notifier.stopping(f"gateway {config.gateway.name} stopping")
        if metrics is not None:
            metrics.stop()
        await asyncio.to_thread(_stop_buses, runners)
        bridge.publish_events()
        bridge.close()
        log.info("gateway %s stopped", config.gateway.name)


def _log_budgets(config: Config) -> None:
    """What each bus's configured traffic takes of it (``busgate check-config`` prints the
    same), and a warning for a bus that cannot carry it."""
    for bus in config.buses:
        budget = bus_budget(bus)
        log.info("%s", budget.summary())
        for warning in budget.warnings():
            log.warning("bus %s: %s", bus.name, warning)


async def _ready_when_open(notifier: Notifier, config: Config,
                           runners: dict[str, BusRunner], stop: asyncio.Event) -> None:
    """READY=1 once every bus is open (the zenoh session already is), with a status line."""
    while not stop.is_set() and not all(r.owner.is_open for r in runners.values()):
        await asyncio.sleep(BUS_OPEN_POLL_S)
    if not stop.is_set():
        devices = sum(len(r.drivers) for r in runners.values())
        notifier.ready(f"gateway {config.gateway.name}: {len(runners)} bus(es) open, "
                       f"{devices} device(s), zenoh up")


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
