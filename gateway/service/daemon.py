"""``busgate run --config FILE``: the daemon.

It loads and checks the config (refusing it with the same messages as ``check-config``),
opens the zenoh session, starts one bus runner per bus (with ``[gateway] workers``, the buses
that move run in worker processes: ``service.workers``) and serves until SIGTERM, SIGINT or
SIGHUP (``STOP_SIGNALS``).
It refuses to start, in one line and with exit status 2, when a port is locked by another
process (retrying would not win it) or zenoh or the metrics endpoint cannot listen where told
(the address is in use: another gateway or demo), before any bus is opened; a port that does
not exist yet only delays its bus, which retries.
Under systemd (Type=notify) it says READY once every bus has had its first attempt to open
(a bus down retries: STATUS says which and why, and follows them), pings the watchdog only
while every bus thread keeps its schedule (and every worker is alive and talking), and says
STOPPING on the way out.
Then it stops in order, within about a second: the streams and the devices (each bus puts its
devices in their safe state and closes, all buses at once; a worker that has not ended after
``STOP_S`` is killed), and the zenoh session last.
With ``[recorder]`` in the config the flight recorder keeps the last seconds of everything and
writes an incident file on an e-stop, a fault, a bus down or SIGUSR1 (``recording.flight``);
without, SIGUSR1 only says so in the log (it never ends the daemon). With ``[ros2]`` the
gateway is a ROS 2 node too, on the same session (``gateway.ros2``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import gc
import logging
import signal
import threading
from collections import deque
from collections.abc import Mapping
from functools import partial
from typing import TYPE_CHECKING, Any

from busgate.errors import BusgateError, BusUnavailableError
from busgate.gateway import installed_version
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.api.doorbell import Doorbell, Mailbox
from busgate.gateway.bus.can_options import unknown_interface
from busgate.gateway.bus.clock import now, tune_interpreter
from busgate.gateway.bus.port_access import LOCKED, NOT_A_DEVICE, port_problem
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.recording.flight import FlightRecorder, Trigger
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service import logs
from busgate.gateway.service.assembly import (
    STOP_TIMEOUT_S,
    build_bus,
    realtime_process,
    stop_together,
)
from busgate.gateway.service.budget import bus_budget
from busgate.gateway.service.metrics import Metrics
from busgate.gateway.service.placement import placement, too_many
from busgate.gateway.service.sdnotify import Notifier, Watchdog
from busgate.gateway.service.workers import WorkerProcess
from busgate.schemas.config import CanBus, Config, ignored_keys, load_config
from busgate.schemas.endpoints import exposure_warnings

if TYPE_CHECKING:
    from busgate.gateway.api.bridge import ZenohBridge
    from busgate.gateway.ros2.face import Ros2Face

log = logging.getLogger("busgate")

BUS_OPEN_POLL_S = 0.01
#: Who holds an address a gateway was told to listen on, most of the time.
IN_USE_HINT = "another busgate demo or run?"
#: What stops the daemon in order: systemd and ``kill`` (SIGTERM), a Ctrl-C (SIGINT), a
#: terminal or ssh session that closes or a habitual ``kill -HUP`` (SIGHUP: nothing is
#: reloaded; left to its default, it ended the daemon at once, the devices as they were).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
#: How often a gateway in client mode tries its routers again while none can be reached.
OPEN_RETRY_S = 2.0
#: How long a stop waits for an opening under way to hand its thread back (``_Opening``).
OPEN_ABANDON_WAIT_S = 2.0
#: How often a gateway waiting for its routers says so in the log.
OPEN_WARN_EVERY_S = 60.0
#: What a start waiting for a router asks systemd for at each try (``EXTEND_TIMEOUT_USEC``):
#: a try that meets a router that takes the connection and never answers lasts 10 s.
OPEN_WAIT_S = OPEN_RETRY_S + 15.0
#: How often a gateway in client mode looks whether it still reaches a router (``_routers``).
ROUTER_CHECK_S = 1.0
#: How often systemd's STATUS is brought up to date (a bus that comes up, or goes down).
STATUS_POLL_S = 0.5
#: How long the start-up line waits for the buses whose ports look openable to be open.
FIRST_OPEN_WAIT_S = 1.0
EVENT_BACKLOG = 10_000
#: New device states waiting for the publisher: two seconds of 20 devices at 100 Hz.
STATE_BACKLOG = 4_096


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    run = subparsers.add_parser(
        "run",
        description="Run the gateway: own the configured buses and serve them over zenoh until "
        "SIGTERM, SIGINT or SIGHUP. Exit status 0 once stopped so, 2 when it refuses to start (an "
        "invalid config, a port or address in use: one line on stderr per problem).",
    )
    run.add_argument("--config", required=True, help="the gateway's TOML config file")
    run.add_argument(
        "--log-level",
        default="info",
        choices=("debug", "info", "warning"),
        help="the least severe log lines written to stderr (the journal under systemd; "
        "default info)",
    )
    run.set_defaults(handler=run_daemon)


def run_daemon(args: argparse.Namespace) -> int:
    logs.configure(args.log_level.upper())
    config = load_config(args.config)
    asyncio.run(serve(config))
    return 0


async def serve(
    config: Config, *, ready: threading.Event | None = None, stop: asyncio.Event | None = None
) -> None:
    """Serve ``config`` until ``stop`` is set (or a stop signal when no ``stop`` is given)."""
    from busgate.gateway.api import bridge as zenoh_side  # the one module that needs zenoh

    expected_up = _check_ports(config)
    tune_interpreter()
    realtime_process(config, "gateway")  # before zenoh's threads and the buses' start
    loop = asyncio.get_running_loop()
    stop = stop or stop_on_signals(loop)
    notifier = Notifier()
    doorbell = Doorbell()  # what fills these wakes the publishing loop
    events: deque[DeviceEvent] = Mailbox(doorbell.ring, maxlen=EVENT_BACKLOG)
    states: deque[tuple[str, dict]] = Mailbox(doorbell.ring, maxlen=STATE_BACKLOG)
    runners = {
        bus.name: build_bus(
            bus,
            on_event=events.append,
            on_state=lambda device, state: states.append((device, state)),
        )
        for bus in config.buses
    }
    workers = _workers(config, runners)
    local = dict(runners)
    for worker in workers:  # a bus in a worker: its runner here is the worker's
        for name, remote in worker.runners.items():
            runners[name] = remote  # type: ignore[assignment]
            del local[name]
    api = GatewayApi(config.gateway.name, runners, on_event=events.append)
    bridge = zenoh_side.ZenohBridge(config, api, runners, events, states, doorbell)
    ros2 = _ros2_face(config, api, bridge)
    recorder = _flight_recorder(config, runners, bridge)  # a folder it cannot write: refused
    _incident_on_sigusr1(loop, recorder)
    # First: a gateway nobody can reach opens no port.
    if not await _session_opened(bridge, loop, stop, notifier):
        log.info("gateway %s stopped before its session opened", config.gateway.name)
        return
    if ros2 is not None:
        ros2.open()
    metrics: Metrics | None = None
    try:
        if config.metrics is not None:  # before the buses too: a refusal leaves them unopened
            metrics = _start_metrics(runners, bridge, config.metrics.listen)
        _log_budgets(config)
        for runner in local.values():
            runner.start()
        if workers:
            log.info("bus workers: %s", "; ".join(f"{w.index}: {w.buses}" for w in workers))
        for worker in workers:
            worker.start()
        await asyncio.to_thread(lambda: [worker.wait_first_word() for worker in workers])
        gc.freeze()  # what start-up made lives for good: keep it out of every collection
        up = await _buses_up(runners, expected_up)
        log.info("gateway %s serving %s, %d up", config.gateway.name, _buses(len(runners)), up)
        if ready is not None:
            ready.set()
        watchdog = Watchdog(notifier, lambda: every_bus_on_schedule(runners))
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(_ready_once_tried(notifier, config, runners, stop))
            tasks.create_task(watchdog.run(stop))
            if recorder is not None:
                tasks.create_task(recorder.run(stop))
            if ros2 is not None:
                tasks.create_task(ros2.run(stop))
            if config.zenoh.mode == "client":
                tasks.create_task(_routers(bridge, stop))
            await bridge.publish_forever(stop)
    finally:
        for worker in workers:  # first: a worker's end read from now on is the stop's own
            worker.stopping()
        notifier.stopping(f"gateway {config.gateway.name} stopping")
        if metrics is not None:
            metrics.stop()
        stops = [partial(r.stop, STOP_TIMEOUT_S) for r in local.values()]
        await asyncio.to_thread(stop_together, [*stops, *(w.stop for w in workers)])
        bridge.put_reports.flush(every=True)
        bridge.publish_events()
        if recorder is not None:  # after the buses: their last frames are in it
            await asyncio.to_thread(recorder.flush)
        if ros2 is not None:
            ros2.close()
        bridge.close()
        log.info("gateway %s stopped", config.gateway.name)


def _ros2_face(config: Config, api: GatewayApi, bridge: ZenohBridge) -> Ros2Face | None:
    """The ROS 2 face on the bridge's session, with ``[ros2]`` in the config."""
    if config.ros2 is None:
        return None
    from busgate.gateway.ros2.face import Ros2Face  # needs zenoh, as the bridge does

    return Ros2Face(config.ros2, api, bridge)


def _flight_recorder(
    config: Config, runners: dict[str, BusRunner], bridge: ZenohBridge
) -> FlightRecorder | None:
    """The flight recorder, fed by the bridge and tapping every bus; ``None`` when the config
    has no ``[recorder]``."""
    if config.recorder is None:
        return None
    recorder = FlightRecorder(
        config.recorder,
        prefix=config.gateway.prefix,
        gateway=config.gateway.name,
        buses={name: list(runner.drivers) for name, runner in runners.items()},
        version=installed_version(),
    )
    recorder.prepare()
    bridge.on_published = recorder.on_published
    bridge.on_command = recorder.on_command
    for name, runner in runners.items():
        runner.owner.tap = recorder.tap(name)
    log.info(
        "flight recorder: the last %g s kept, incidents written to %s",
        config.recorder.seconds,
        config.recorder.dir,
    )
    return recorder


def _incident_on_sigusr1(loop: asyncio.AbstractEventLoop, recorder: FlightRecorder | None) -> None:
    """SIGUSR1 asks for an incident file; without a recorder it is said so, and nothing ends."""

    def asked() -> None:
        if recorder is None:
            log.warning("SIGUSR1: no flight recorder ([recorder] in the config turns it on)")
        else:
            recorder.trigger(Trigger("signal", "SIGUSR1 from an operator"))

    with contextlib.suppress(NotImplementedError, RuntimeError):
        loop.add_signal_handler(signal.SIGUSR1, asked)


def _check_ports(config: Config) -> set[str]:
    """The buses whose device files look openable now. A file another process holds, a path
    that is no serial port, or a CAN interface python-can does not have, is refused
    (``BusUnavailableError``); a port missing or not ours to open is logged with what to do,
    and its bus retries."""
    expected_up = set()
    for bus in config.buses:
        if isinstance(bus, CanBus) and (unknown := unknown_interface(bus.interface)):
            raise BusUnavailableError(f"bus {bus.name}: {unknown}")  # retrying would not help
        problem = port_problem(bus.device_key[1]) if bus.device_key is not None else None
        if problem is None:
            expected_up.add(bus.name)
        elif problem.kind in (LOCKED, NOT_A_DEVICE):  # retrying would not change it
            raise BusUnavailableError(f"bus {bus.name}: {problem.message}")
        else:
            log.warning("bus %s: %s", bus.name, problem.message)
    return expected_up


async def _session_opened(
    bridge: ZenohBridge, loop: asyncio.AbstractEventLoop, stop: asyncio.Event, notifier: Notifier
) -> bool:
    """Open the bridge's zenoh session: whether it opened (``False``: stopped first). The
    opening runs on a thread of its own, so that a stop signal is heard at once (zenoh waits
    10 s for a router that took the connection and never answers: all of systemd's
    ``TimeoutStopSec``). A gateway in client mode whose routers cannot be reached yet (a robot
    that boots before its router) tries again every ``OPEN_RETRY_S``, saying so, and asks
    systemd for the time; before, it exited, and the unit's start limit left it failed.
    Any other refusal of zenoh's is one line (``ConnectError``)."""
    from busgate.client.errors import ConnectError  # the client's package loads zenoh

    client_mode = bridge.config.zenoh.mode == "client"
    routers = _routers_named(bridge)
    waiting_since = told_at = None
    while True:
        opening = _Opening(bridge, loop)
        stopped: asyncio.Future[Any] = asyncio.ensure_future(stop.wait())
        try:
            await asyncio.wait((opening.done, stopped), return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            await opening.abandon()
            raise
        finally:
            stopped.cancel()
        if not opening.done.done():
            await opening.abandon()
            return False
        try:
            opening.done.result()
            return True
        except ConnectError as exc:
            if not (client_mode and exc.unreached):
                raise
            moment = now()
            waiting_since = waiting_since or moment
            told = f"no router reached at {routers}: trying again every {OPEN_RETRY_S:g} s"
            if told_at is None or moment - told_at >= OPEN_WARN_EVERY_S:  # not a line a try
                told_at = moment
                log.warning("zenoh: %s (for %.0f s now; %s)", told, moment - waiting_since, exc)
            notifier.notify(f"EXTEND_TIMEOUT_USEC={int(OPEN_WAIT_S * 1e6)}", f"STATUS={told}")
        if await _stopped_within(stop, OPEN_RETRY_S):
            return False


class _Opening:
    """One try at the bridge's session, on a daemon thread of its own; ``done``, the loop's
    future of it: zenoh's refusal as one line (``ConnectError``, ``unreached`` when no
    endpoint could be reached), with what was opened closed again (``close_session``: the
    next try opens it anew)."""

    def __init__(self, bridge: ZenohBridge, loop: asyncio.AbstractEventLoop) -> None:
        self.done: asyncio.Future[None] = loop.create_future()
        self._bridge, self._loop = bridge, loop
        self._lock = threading.Lock()
        self._abandoned = False
        self._ended: tuple[BaseException | None] | None = None  # (its refusal,) once it ended
        self._thread = threading.Thread(target=self._open, name="zenoh-open", daemon=True)
        self._thread.start()

    async def abandon(self) -> None:
        """Give the try up (the gateway stops before its session opened): the session is
        closed should it open after all, by whichever of the two threads sees it last. The
        thread is waited for ``OPEN_ABANDON_WAIT_S`` at most: a process that ends while zenoh
        is handing a thread back aborts (its return into a finalizing interpreter: "FATAL:
        exception not rethrown", in 9 of 10 stops that came as a router answered)."""
        with self._lock:
            self._abandoned, ended = True, self._ended
        self.done.cancel()
        if ended is not None:  # it ended first: only this thread knows the session is unused
            if ended[0] is None:
                self._bridge.close()
            return
        deadline = now() + OPEN_ABANDON_WAIT_S
        while self._thread.is_alive() and now() < deadline:
            await asyncio.sleep(0.01)

    def _open(self) -> None:
        import zenoh

        from busgate.client.errors import ConnectError
        from busgate.schemas.zenoh_session import UNREACHED, session_refusal

        refusal: BaseException | None = None
        try:
            self._bridge.open(self._loop)
        except zenoh.ZError as exc:
            reason = session_refusal(exc, IN_USE_HINT)
            refusal = ConnectError(reason, unreached=UNREACHED in str(exc))
        except BusgateError as exc:  # a namesake live (``ConfigError``)
            refusal = exc
        except ValueError as exc:  # no zenoh config file, a Unix socket zenoh would take over
            refusal = ConnectError(str(exc))
        except Exception as exc:  # a bug: raised where the opening is awaited, never lost
            refusal = exc
        if refusal is not None:
            self._bridge.close_session()
        with self._lock:
            self._ended, abandoned = (refusal,), self._abandoned
        if abandoned:  # nobody waits for it: what opened after all closes here
            if refusal is None:
                self._bridge.close()
            return
        with contextlib.suppress(RuntimeError):  # the loop ended first: the process ends
            self._loop.call_soon_threadsafe(self._settle, refusal)

    def _settle(self, refusal: BaseException | None) -> None:
        if self.done.done():  # abandoned meanwhile: ``abandon`` saw it end, and closed it
            return
        if refusal is None:
            self.done.set_result(None)
        else:
            self.done.set_exception(refusal)


async def _routers(bridge: ZenohBridge, stop: asyncio.Event) -> None:
    """A gateway in client mode reaches its clients through its routers only: the moment it
    reaches none, and the moment it reaches one again, are logged (zenoh connects again by
    itself; the buses go on meanwhile, and a follow stream whose client cannot reach it goes
    stale as any other). Looked at every ``ROUTER_CHECK_S``."""
    endpoints = _routers_named(bridge)
    lost_at: float | None = None
    while not await _stopped_within(stop, ROUTER_CHECK_S):
        reached = bridge.routers() > 0
        if not reached and lost_at is None:
            lost_at = now()
            log.warning(
                "zenoh: no router reached at %s any more: no client reaches this gateway until "
                "one is back (zenoh connects again by itself; the buses go on)",
                endpoints,
            )
        elif reached and lost_at is not None:
            log.info(
                "zenoh: a router reached again at %s, after %.0f s without",
                endpoints,
                now() - lost_at,
            )
            lost_at = None


def _routers_named(bridge: ZenohBridge) -> str:
    """Where a gateway in client mode looks for its routers, as its log lines name it."""
    return ", ".join(bridge.config.zenoh.connect) or "the config file's endpoints"


async def _stopped_within(stop: asyncio.Event, seconds: float) -> bool:
    """Whether ``stop`` is set within ``seconds``."""
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), seconds)
    return stop.is_set()


def _start_metrics(runners: dict[str, BusRunner], bridge: ZenohBridge, listen: str) -> Metrics:
    """The Prometheus endpoint on ``listen``; a refusal (the address in use …) is one line."""
    try:
        metrics = Metrics(runners, clients=bridge.connections).start(listen)
    except OSError as exc:
        hint = f" ({IN_USE_HINT})" if exc.errno == errno.EADDRINUSE else ""
        raise BusgateError(f"metrics cannot listen on {listen}: {exc.strerror}{hint}") from exc
    bridge.on_latency = metrics.observe
    log.info("metrics on http://%s/metrics", listen)
    return metrics


def every_bus_on_schedule(runners: Mapping[str, BusRunner]) -> bool:
    """Whether every bus thread keeps its schedule (the watchdog's ping goes); a warning names
    those that do not, each time the ping is held back: systemd's watchdog timeout, a while
    later, names none."""
    late = [name for name, runner in runners.items() if not runner.keeping_schedule()]
    if late:
        log.warning(
            "watchdog: not pinged, bus %s not keeping its schedule (systemd restarts the "
            "service if it goes on)",
            ", ".join(late),
        )
    return not late


async def _buses_up(runners: dict[str, BusRunner], expected_up: set[str]) -> int:
    """How many buses are open, once those expected up are (or ``FIRST_OPEN_WAIT_S``
    has passed)."""
    deadline = now() + FIRST_OPEN_WAIT_S
    while not all(runners[name].owner.is_open for name in expected_up) and now() < deadline:
        await asyncio.sleep(BUS_OPEN_POLL_S)
    return sum(runner.owner.is_open for runner in runners.values())


def _buses(count: int) -> str:
    return f"{count} bus" if count == 1 else f"{count} buses"


def _log_budgets(config: Config) -> None:
    """What each bus's configured traffic takes of it (``busgate check-config`` prints the
    same), and a warning for a bus that cannot carry it, for a listener any host can reach
    with nothing to keep it from moving the devices, and for a joint table's ignored key."""
    exposed = exposure_warnings(config.zenoh.listen, config.zenoh.config_file)
    for warning in exposed + ignored_keys(config):
        log.warning("%s", warning)
    for bus in config.buses:
        budget = bus_budget(bus)
        log.info("%s", budget.summary())
        for warning in budget.warnings():
            log.warning("bus %s: %s", bus.name, warning)


async def _ready_once_tried(
    notifier: Notifier, config: Config, runners: dict[str, BusRunner], stop: asyncio.Event
) -> None:
    """READY=1 once every bus has had its first attempt to open, open or not (the zenoh
    session is up already), and STATUS kept saying which buses are down and why. A bus down
    (its adapter unplugged) retries by itself; held back for it, READY never came and systemd
    killed the whole gateway at TimeoutStartSec, its healthy buses brought to their safe state
    each time."""
    while not stop.is_set() and not all(_tried(r) for r in runners.values()):
        await asyncio.sleep(BUS_OPEN_POLL_S)
    if stop.is_set():
        return
    down = _down(runners)
    notifier.ready(_status_line(config, runners, down))
    if down:
        log.warning("ready with %s down, retrying: %s", _buses(len(down)), _why(down))
    while not await _stopped_within(stop, STATUS_POLL_S):
        if (now_down := _down(runners)) != down:
            down = now_down
            notifier.status(_status_line(config, runners, down))


def _tried(runner: BusRunner) -> bool:
    """The bus has had its first attempt to open: it is open, or why not is known."""
    return runner.owner.is_open or runner.open_failure is not None


def _down(runners: dict[str, BusRunner]) -> dict[str, str]:
    """Each bus not open, and why (a bus lost has not failed to open again yet)."""
    return {
        name: runner.open_failure or "lost, opening it again"
        for name, runner in runners.items()
        if not runner.owner.is_open
    }


def _why(down: dict[str, str]) -> str:
    return "; ".join(f"bus {name} down: {why}" for name, why in down.items())


def _status_line(config: Config, runners: dict[str, BusRunner], down: dict[str, str]) -> str:
    """systemd's STATUS: how many buses are open, and why each other is not."""
    devices = sum(len(r.drivers) for r in runners.values())
    opened = f"{len(runners) - len(down)} of " if down else ""
    line = f"gateway {config.gateway.name}: {opened}{len(runners)} bus(es) open, "
    line += f"{devices} device(s), zenoh up"
    return f"{line}; {_why(down)}" if down else line


def _workers(config: Config, runners: dict[str, BusRunner]) -> list[WorkerProcess]:
    """The bus workers ``[gateway] workers`` asks for (none: every bus here), each given the
    buses ``placement`` chose, whose runners here become their shadows (``service.workers``)."""
    groups = placement(config)
    if (crowded := too_many(len(groups))) is not None:
        log.warning("%s", crowded)
    return [
        WorkerProcess(index, config, [runners[name] for name in group])
        for index, group in enumerate(groups)
    ]


def stop_on_signals(loop: asyncio.AbstractEventLoop) -> asyncio.Event:
    """An event set on any of ``STOP_SIGNALS``, each logged by name."""
    stop = asyncio.Event()
    for sig in STOP_SIGNALS:
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, _stop_on, sig, stop)
    return stop


def _stop_on(sig: signal.Signals, stop: asyncio.Event) -> None:
    log.info("%s: stopping", sig.name)
    stop.set()
