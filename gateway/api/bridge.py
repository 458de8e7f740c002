"""The zenoh side of the daemon: key expressions in, the gateway API, replies and telemetry out.

Rules of this file:

1. Zenoh callbacks run on zenoh's threads and only hand work over: a command is validated and
   handed to its bus runner (non-blocking), a follow target is stored, an e-stop is queued
   ahead of everything (before its payload, which only names its sender, is read). Replies,
   publications and liveliness changes happen on the asyncio loop's thread, never on a bus
   thread or inside a zenoh callback.
2. Every query gets exactly one reply, then is dropped. The buses answer every command in
   bounded time (a deadline to start, a bounded duration once started); should one not have
   finished in ``REPLY_TIMEOUT_S`` all the same (a bug), its future is cancelled, so that it
   is never carried out, and it is answered ``internal``.
3. Telemetry publishers use congestion control DROP: a slow subscriber never stalls a bus.
4. The session is closed last, after the buses have put their devices in a safe state, and
   waited for ``CLOSE_WAIT_S`` at most (``close_within``): zenoh's close waits for a connect
   under way, which to a router that took the connection and never answers is 10 s, all of
   systemd's ``TimeoutStopSec``; the stop took that long, and systemd called it a failure.
5. A command is taken only on a key that names it: its leaf as declared (``cmd``,
   ``follow``, ``twist``: a wildcard leaf reaches several handlers at once), the trajectory
   and the e-stop's reset on this gateway's own key. Only the gateway's name may be a
   wildcard (a fleet's command: each gateway with the device answers). A query that names
   nothing here is dropped unanswered (rule 2's one exception), left to those it names; one
   with a wildcard where its key names this gateway's device, bus, base or trajectory key is
   refused ``bad_command`` once, unless it reaches the info key too (which answers it).
6. A flood of puts or gets never holds up an e-stop. Every key a client puts or gets on
   but the e-stop's, and the clients' liveliness tokens, are taken through an ``Intake``
   (``intake`` rules): zenoh's receiving threads never wait on Python, and the e-stop and
   its reset run on the receiving thread itself, with no thread of ours to wake. What still
   waits for its intake's thread when an e-stop comes was put before it: commands, follow
   targets, twists and trajectory commands so waiting are never carried out, so that none
   moves a device after a reset that follows at once (a query is answered ``estopped``, a
   put dropped); a play already in its lane when an e-stop came is refused ``estopped`` as
   it would start (``intake`` rule 5). A ring is one a key, for every device: a flood past
   what its thread takes (thousands of commands, tens of thousands of follow targets a
   second) drops other devices' puts and queries on that key too. Two clients putting on a
   ``cmd`` key as fast as they could held an e-stop 0.2-2 s before it reached the buses; two
   flooding follow targets, 48-62 ms at the median (docs/performance.md, "An e-stop under a
   flood of follow targets", "... of commands").
7. One gateway a name under a prefix: two of one name would both carry out every command sent
   to it, each answering ok. Before it declares anything the gateway asks, once its session
   is open, for its own liveliness token and its own ``info`` (both at once, at most
   ``LIVE_WAIT_S``, the wait of ``busgate replay``'s check of its prefix); another session
   answering its ``info`` refuses the start (``ConfigError``), with the session closed
   again. A token held with no ``info`` answering is a gateway's whose host went away (its
   token outlives it until its lease runs out): warned of, and the start goes on, else a
   restart after a power loss would be refused until then. One that comes later (the two
   could not reach each other at the start, or started together) is looked for whenever
   zenoh tells that this gateway's ``info`` is served elsewhere or its token came (zenoh
   tells one or the other, not always both, since the token is held here too): ``info`` is
   asked of the other sessions, and each that answers is logged once, an ERROR naming it.
   Neither can stop the other.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import asdict
from typing import Any

import zenoh

from busgate.errors import CommandError, ConfigError, RefusedError
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.api.doorbell import Doorbell
from busgate.gateway.api.estop_payload import estop_sender, reset_sender
from busgate.gateway.api.intake import (
    BACKLOG,
    Intake,
    backlog_for,
    take_liveliness,
    take_puts,
    take_queries,
)
from busgate.gateway.api.joints import JointsFeed
from busgate.gateway.api.put_reports import TOLD_LINES, PutReports, log_told
from busgate.gateway.api.taken import estops_when_taken
from busgate.gateway.base.bases import Bases
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.scheduler.outcomes import cancelled_by_estop, settled
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.lanes import TrajectoryLanes
from busgate.gateway.trajectory.playing import Trajectories
from busgate.schemas.config import Config
from busgate.schemas.encoding import message_json
from busgate.schemas.keys import Keys
from busgate.schemas.payload import MAX_PAYLOAD, too_large
from busgate.schemas.replies import error_reply
from busgate.schemas.trajectory import MAX_TRAJECTORY_PAYLOAD
from busgate.schemas.validation import shown
from busgate.schemas.zenoh_session import (
    CLOSE_WAIT_S,
    LIVE_WAIT_S,
    NOBODY_REACHES,
    close_within,
    endpoints_of,
    gateway_session_config,
)

log = logging.getLogger(__name__)

#: A query taken: the (concrete) key its reply goes on, its payload, and what carries it out.
Routed = tuple[str, bytes, Callable[[], Future]]
#: What a query names here (``None``: nothing, and it was dropped), read off it.
Route = Callable[[zenoh.Query], Routed | None]

REPLY_TIMEOUT_S = 10.0
#: A get of this gateway's ``info`` asked of the other sessions (rule 7): every answer, none
#: merged into another (two gateways of one name answer on one key).
_OTHERS: dict[str, Any] = {
    "target": zenoh.QueryTarget.ALL,
    "consolidation": zenoh.ConsolidationMode.NONE,
    "timeout": LIVE_WAIT_S,
    "allowed_destination": zenoh.Locality.REMOTE,
}
#: The publishing round's period while it has timed work of its own (``_round_due``): a
#: trajectory's verdicts, a base's wheels, a refusal held back.
PUBLISH_EVERY_S = 0.005
#: The round's period while only telemetry and events come, unless the joints message is due
#: more often (a device polled faster): each round is a wake-up of this loop and of zenoh's
#: sending thread, and at 5 ms they cost 20 heartbeating devices some 3 points of a core more
#: than at 10 ms (docs/performance.md). A state carries the time it was read; it reaches
#: clients up to a round later.
TELEMETRY_EVERY_S = 0.01
#: The longest wait of a loop with no work: its doorbell cuts it short (``doorbell``).
IDLE_WAIT_S = 0.1
STATS_EVERY_S = 1.0
#: What a command key's name names, in each room (``_ours``).
ROOM_NOUNS = {"dev": "device", "bus": "bus", "base": "base"}


class ZenohBridge:
    """One zenoh session serving one gateway's API."""

    def __init__(
        self,
        config: Config,
        api: GatewayApi,
        runners: dict[str, BusRunner],
        events: deque[DeviceEvent],
        states: deque[tuple[str, dict[str, Any]]],
        doorbell: Doorbell | None = None,
    ) -> None:
        self.config = config
        self.api = api
        self.runners = runners
        #: The API's keys (``schemas.keys``), and this gateway's name in them.
        self.keys, self.name = Keys(config.gateway.prefix), config.gateway.name
        self._estop_key = zenoh.KeyExpr(self.keys.estop(self.name))
        self.events = events  # filled by the bus threads and the API, drained here
        self.states = states  # every new device state, filled by the bus threads, drained here
        #: Rung by what fills ``events`` and ``states`` (``doorbell.Mailbox``): a loop with no
        #: work waits for it.
        self.doorbell = doorbell or Doorbell()
        #: Called with each command's time from query to reply (the metrics' histogram).
        self.on_latency: Callable[[float], None] = ignored
        #: Called with every message published: key, body, and the bytes sent (the flight
        #: recorder's ring); on the loop's thread.
        self.on_published: Callable[[str, dict[str, Any], bytes], None] = ignored
        #: Called with every command (key, payload), its reply (``None`` for what gets none:
        #: an e-stop, a follow target taken) and when it came (``None``: now; an e-stop's
        #: frames may go before it is told); on the thread that has the reply.
        self.on_command: Callable[[str, bytes, dict[str, Any] | None, float | None], None] = ignored
        #: Called with every joints message published (the ROS face's joint states); on the
        #: loop's thread.
        self.on_joints: Callable[[dict[str, Any]], None] = ignored
        #: Called with each base's name and odometry as published (the ROS face's odom).
        self.on_odometry: Callable[[str, dict[str, Any]], None] = ignored
        self._loop: asyncio.AbstractEventLoop | None = None
        self._session: zenoh.Session | None = None
        self._keep: list[Any] = []
        self._intakes: list[Intake] = []  # rule 6
        #: The intakes whose waiting puts and queries an e-stop takes (rule 6), each with the
        #: route of its queries (``None``: puts).
        self._before_estop: list[tuple[Intake, Route | None]] = []
        #: Called on the e-stop's thread once every bus has it (the ROS face's commands not
        #: yet handed on, dropped as ours are).
        self.at_estop: list[Callable[[], None]] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        #: What asks the other sessions for this gateway's ``info`` (rule 7), and the
        #: sessions of this gateway's name already logged.
        self._namesakes: zenoh.Querier | None = None
        self._namesakes_told: set[str] = set()
        self._device_tokens: dict[str, Any] = {}
        self._state_keys: dict[str, str] = {}  # each device's state key, written once
        #: A refused put's event, at most one a device or base every 0.1 s, an e-stop's and a
        #: reset's, at most one of each every 0.1 s: the rest counted (``put_reports``).
        self.put_reports = PutReports(
            frozenset([*api.devices, *(b.name for b in config.bases)]), self._tell_put
        )
        api.driven_by = lambda device: self.bases.driving_wheel(device)
        self.trajectories = Trajectories(
            api,
            f"{config.gateway.prefix}/{self.name}",
            self._put_any,
            lambda event: self.events.append(event),
            driven_by=api.driven_by,
        )
        #: Trajectory commands run here, off zenoh's threads and the loop (a 1 MiB play is
        #: parsed and checked whole): plays in their lane, cancels and status in another.
        self._trajectory_lanes = TrajectoryLanes(self.trajectories.command)
        fastest_poll_hz = max(d.poll_hz for bus in config.buses for d in bus.devices)
        self.bases = Bases(
            config.bases,
            api,
            lambda event: self.events.append(event),
            self._odometry,
            self.trajectories,
            estop_reset_key=self.keys.estop_reset(self.name),
        )
        self.joints = JointsFeed(
            config.gateway.name,
            (driver for _, driver in api.devices.values()),
            min_interval_s=1 / fastest_poll_hz,
        )
        self.telemetry_every_s = min(TELEMETRY_EVERY_S, self.joints.min_interval_s)

    # -- lifetime ---------------------------------------------------------------------------

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        """Open the session and declare every key of the API; ``ConfigError``, with nothing
        declared and the session closed, when a gateway of this name is live (rule 7)."""
        self._loop = loop
        zenoh_section = self.config.zenoh
        config = gateway_session_config(zenoh_section)
        self._session = session = zenoh.open(config)
        self._refuse_namesakes(session)
        keys, gw = self.keys, self.name
        commands, puts = self._commands, self._puts
        self._before_estop = []
        self._intakes = [
            commands(session, keys.device(gw, "*", "cmd"), self._device_query, "device-commands"),
            puts(session, keys.device(gw, "*", "cmd"), self._command_puts("dev"), "device-puts"),
            puts(session, keys.device(gw, "*", "follow"), self._on_follow, "follow-targets"),
            commands(session, keys.bus(gw, "*", "cmd"), self._bus_query, "bus-commands"),
            commands(
                session,
                keys.trajectory(gw),
                self._trajectory_query,
                "trajectories",
                backlog_for(MAX_TRAJECTORY_PAYLOAD),
            ),
            commands(session, keys.base(gw, "*", "cmd"), self._base_query, "base-commands"),
            puts(session, keys.base(gw, "*", "cmd"), self._command_puts("base"), "base-puts"),
            puts(session, keys.base(gw, "*", "twist"), self._on_twist, "twists"),
            take_queries(session, keys.info(gw), self._on_info, "info"),
            take_liveliness(session, keys.client("*"), self._on_client, "clients"),
        ]
        self._keep = [
            session.declare_subscriber(
                f"{keys.estop(gw)}/**",
                zenoh.handlers.Callback(self._on_estop_or_reset, indirect=False),
            ),
            session.liveliness().declare_token(keys.alive(gw)),
            *self._watch_namesakes(session),
        ]
        drop = zenoh.CongestionControl.DROP
        published = [
            *(
                keys.device(gw, device, kind)
                for device in self.api.devices
                for kind in ("state", "event")
            ),
            *(keys.bus(gw, bus, "stats") for bus in self.runners),
            keys.joints(gw),
            *(keys.base(gw, name, "odom") for name in self.bases.bases),
        ]
        for key in published:  # each dropped when late: the next one says it again
            self._publishers[key] = session.declare_publisher(key, congestion_control=drop)
        self._publishers[keys.events(gw)] = session.declare_publisher(keys.events(gw))
        listening = endpoints_of(config, "listen", zenoh_section.mode)  # a config file's too
        where = ", ".join(listening) or "no endpoint: reachable only through connect"
        log.info("zenoh session up: gateway %s/%s, listening on %s", keys.prefix, gw, where)
        connecting = endpoints_of(config, "connect", zenoh_section.mode)
        if not (listening or connecting or zenoh_section.multicast_scouting):
            log.warning("zenoh: %s", NOBODY_REACHES)

    def _refuse_namesakes(self, session: zenoh.Session) -> None:
        """``ConfigError`` when another session answers this gateway's ``info`` (rule 7),
        the session closed first; a warning when its liveliness token is held with no
        ``info`` answering (a stale one). Asked before anything is declared, the two at once."""
        name, prefix = self.config.gateway.name, self.config.gateway.prefix
        tokens = session.liveliness().get(self.keys.alive(name), timeout=LIVE_WAIT_S)
        infos = session.get(self.keys.info(name), **_OTHERS)
        held = any(reply.ok is not None for reply in tokens)
        answering = {str(r.replier_id.zid) for r in infos if r.ok is not None and r.replier_id}
        if not answering:
            if held:  # a gateway serving the name answers its info: this one is stale
                log.warning(
                    "the token %s is held, but no gateway of name %s answers its info: "
                    "taken for one whose host went away, its token kept until its lease runs "
                    "out; serving",
                    self.keys.alive(name),
                    name,
                )
            return
        others = "; ".join(_session_named(session, zid) for zid in sorted(answering))
        self._session = None
        close_within(session)
        raise ConfigError(
            f"gateway {name} is already live under prefix {prefix} ({others}): two "
            "gateways of one name both carry out every command sent to it; give each gateway "
            "its own [gateway] name (or stop the other). Nothing was declared",
            path="gateway.name",
        )

    def _watch_namesakes(self, session: zenoh.Session) -> list[Any]:
        """What tells of a gateway of this name that comes later (rule 7): a querier of the
        other sessions' ``info``, whose status turns matching when one serves it, and a
        subscriber of this gateway's liveliness token; each hands a look to the loop."""
        self._namesakes = querier = session.declare_querier(self.keys.info(self.name), **_OTHERS)

        def matching(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                self.call_soon(self._ask_namesakes)

        def token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                self.call_soon(self._ask_namesakes)

        watching = [
            querier,
            querier.declare_matching_listener(zenoh.handlers.Callback(matching, indirect=False)),
            session.liveliness().declare_subscriber(
                self.keys.alive(self.name), zenoh.handlers.Callback(token, indirect=False)
            ),
        ]
        status: Any = querier.matching_status  # a MatchingStatus (zenoh's stub says bool)
        if getattr(status, "matching", status):  # one came since _refuse_namesakes asked
            self.call_soon(self._ask_namesakes)
        return watching

    def _ask_namesakes(self) -> None:
        """Ask the other sessions for this gateway's ``info`` (the loop's thread); those that
        answer go to ``_tell_namesakes``."""
        querier = self._namesakes
        if querier is None or self._session is None:
            return
        answering: list[str] = []

        def reply(answer: zenoh.Reply) -> None:
            if answer.ok is not None and answer.replier_id is not None:
                answering.append(str(answer.replier_id.zid))

        with contextlib.suppress(zenoh.ZError):  # the session closing
            querier.get(
                zenoh.handlers.Callback(
                    reply, lambda: self.call_soon(self._tell_namesakes, answering), indirect=False
                )
            )

    def _tell_namesakes(self, answering: list[str]) -> None:
        """An ERROR for each session serving this gateway's name not told yet (rule 7)."""
        session = self._session
        if session is None:
            return
        for zid in sorted(set(answering) - self._namesakes_told):
            self._namesakes_told.add(zid)
            log.error(
                "another gateway named %s is live under prefix %s (%s): both carry out every "
                "command sent to %s, and neither can stop the other; give one of them its own "
                "[gateway] name and restart it",
                self.config.gateway.name,
                self.config.gateway.prefix,
                _session_named(session, zid),
                self.config.gateway.name,
            )

    def _commands(
        self, session: zenoh.Session, key: str, route: Route, name: str, backlog: int = BACKLOG
    ) -> Intake:
        """The queries on ``key``, each answered by carrying out what ``route`` reads off it;
        those waiting when an e-stop comes, refused (rule 6)."""
        intake = take_queries(session, key, self._answering(route), name, backlog, self._estops)
        self._before_estop.append((intake, route))
        return intake

    def _puts(
        self, session: zenoh.Session, key: str, handle: Callable[[zenoh.Sample], None], name: str
    ) -> Intake:
        """The puts on ``key``, each handed to ``handle``; those waiting when an e-stop comes,
        dropped (rule 6)."""
        intake = take_puts(session, key, handle, name, estops=self._estops)
        self._before_estop.append((intake, None))
        return intake

    def _estops(self) -> int:
        """The e-stops so far, for what the intakes take (``intake`` rule 5)."""
        return self.api.estops

    @property
    def session(self) -> zenoh.Session:
        """The open session (the ROS face lives on it too)."""
        assert self._session is not None, "open() first"
        return self._session

    def routers(self) -> int:
        """The zenoh routers the session reaches now."""
        return len(self._session.info.routers_zid()) if self._session is not None else 0

    def connections(self) -> int:
        """Open zenoh transports: the clients, peers and routers connected now."""
        return len(self._session.info.transports()) if self._session is not None else 0

    def close(self) -> None:
        """Undeclare everything and close the session (last, at shutdown)."""
        self._trajectory_lanes.close()
        self.close_session()

    def close_session(self) -> None:
        """Undeclare the keys and close the session, keeping what ``open`` does not make
        again (the trajectory lanes): an opening refused, to be tried again."""
        for intake in self._intakes:
            intake.close()
        session, self._session = self._session, None
        self._namesakes = None
        self._device_tokens.clear()
        self._publishers.clear()
        self._keep.clear()
        if session is not None and not close_within(session):
            log.warning(
                "the zenoh session did not close within %g s (a connect under way to an "
                "endpoint that does not answer): the gateway ends without waiting for it",
                CLOSE_WAIT_S,
            )
        for intake in self._intakes:
            intake.join()

    async def publish_forever(self, stop: asyncio.Event) -> None:
        """Telemetry and events as they come (in rounds of ``telemetry_every_s`` while they
        come, of ``PUBLISH_EVERY_S`` while the round has timed work, else as soon as a state
        or an event comes), bus statistics once a second."""
        next_stats = 0.0
        while not stop.is_set():
            published = self._has_news()
            self.publish_states()
            self.trajectories.tick()
            self.bases.tick()
            self.put_reports.flush()
            self.publish_events()
            if now() >= next_stats:
                next_stats = now() + STATS_EVERY_S
                self.publish_stats()
            # a sleep is cheaper than a wait_for task every round
            if self._round_due():
                await asyncio.sleep(PUBLISH_EVERY_S)
            elif published:
                await asyncio.sleep(self.telemetry_every_s)
            else:
                joints_in = self.joints.due_in(now())
                idle_s = IDLE_WAIT_S if joints_in is None else min(IDLE_WAIT_S, joints_in)
                await self.doorbell.wait(idle_s, self._has_news)

    def _round_due(self) -> bool:
        """Whether the next round has work whatever comes: a trajectory's feedback, a base's
        drive, a refusal, e-stop or reset held back for its interval. (A joints message held
        back for its own is due at a moment the wait is given.)"""
        return self.trajectories.running or self.bases.driving or self.put_reports.withheld

    def _has_news(self) -> bool:
        return bool(self.states or self.events)

    # -- zenoh callbacks (zenoh's threads: hand over only) ----------------------------------

    def _answering(self, route: Route) -> Callable[[zenoh.Query], None]:
        """A handler that answers each query ``route`` takes by carrying it out."""

        def answer(query: zenoh.Query) -> None:
            routed = route(query)
            if routed is not None:
                key, payload, carry_out = routed
                self._answer(query, carry_out, key, payload)

        return answer

    def _device_query(self, query: zenoh.Query) -> Routed | None:
        device = self._ours(query, "dev", self.api.devices)
        if device is None:
            return None
        key = self.keys.device(self.name, device, "cmd")
        return _routed(key, query, lambda payload: self.api.command(device, payload))

    def _bus_query(self, query: zenoh.Query) -> Routed | None:
        bus = self._ours(query, "bus", self.runners)
        if bus is None:
            return None
        key = self.keys.bus(self.name, bus, "cmd")
        return _routed(key, query, lambda payload: self.api.bus_command(bus, payload))

    def _named(self, key: str, room: str, leaf: str) -> str | None:
        """The name in a key of the shape ``<prefix>/<gw>/<room>/<name>/<leaf>``; ``None`` for
        a key of another shape (``**`` matches every key: it names no device) or another leaf
        (a wildcard leaf, ``<prefix>/<gw>/dev/la1/*``, names no command: it would reach cmd
        and follow alike)."""
        chunks = key.split("/")
        if (
            len(chunks) != self.keys.prefix.count("/") + 5
            or chunks[-3] != room
            or chunks[-1] != leaf
        ):
            return None
        return chunks[-2]

    def _ours(self, query: zenoh.Query, room: str, known) -> str | None:
        """The device, bus or base ``query`` names; ``None`` when a query with wildcards names
        nothing of this gateway (``busgate/*/dev/la9/cmd`` sent to a fleet, or ``**``): it is
        left to the gateways that have it, dropped without a reply; unless its wildcard
        stands where a command names one of this gateway's (``dev/*/cmd``, ``dev/la1/*``,
        ``base/**``): refused, once a gateway, rather than left to wait out its timeout."""
        key = str(query.key_expr)
        name = self._named(key, room, "cmd")
        if name is not None and (name in known or "*" not in key):
            return name
        reached = self._one_of_many(query.key_expr, room, known)
        if reached is None:
            query.drop()
            return None
        self._refuse_wildcard(
            query,
            f"{shown(key)} has a wildcard where a command names one {ROOM_NOUNS[room]} and its "
            f"cmd key (such as {reached}): send it to one. Nothing was sent",
            reached,
        )
        return None

    def _refuse_wildcard(self, query: zenoh.Query, why: str, reached: str) -> None:
        """``query``, whose wildcard reached ``reached``, refused ``bad_command`` (rule 5)."""
        refused = CommandError(why)
        self._answer(query, lambda: settled(error_reply(refused)), reached)

    def _one_of_many(self, asked: zenoh.KeyExpr, room: str, known) -> str | None:
        """The first of this gateway's ``room`` command keys that ``asked`` reaches, unless it
        reaches the info key too (``**``, ``busgate/demo/**``: the info answers those,
        once)."""
        if self._reaches_info(asked):
            return None
        keys = (self.keys.room(self.name, room, name, "cmd") for name in known)
        return next((key for key in keys if asked.intersects(zenoh.KeyExpr(key))), None)

    def _reaches_info(self, asked: zenoh.KeyExpr) -> bool:
        """Whether a query on ``asked`` reaches this gateway's info, which answers it (rule 5:
        ``**``, ``busgate/demo/**``), once."""
        return asked.intersects(zenoh.KeyExpr(self.keys.info(self.name)))

    def _base_query(self, query: zenoh.Query) -> Routed | None:
        name = self._ours(query, "base", self.bases.bases)
        if name is None:
            return None
        key = self.keys.base(self.name, name, "cmd")
        return _routed(key, query, lambda payload: self.bases.command(name, payload))

    def _on_twist(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        name = self._named(key, "base", "twist")
        if name is None:
            log.debug("twist on %s names no base: dropped", key)
            return
        payload = self._put_payload(name, key, sample)
        if payload is not None:
            self._report_put(name, key, payload, self.bases.twist(name, payload))

    def _on_info(self, query: zenoh.Query) -> None:
        """The gateway's info; a get that carries a payload (a command sent on ``**`` or
        ``busgate/<gw>/*``, which reaches only this key: the device keys take no wildcard) is
        told so, never answered with an info that reads as the command's success."""
        key = self.keys.info(self.name)
        if query.payload is not None and len(query.payload):
            refused = CommandError(
                f"{key} takes no payload: this get ({str(query.key_expr)[:200]}) carried one, "
                "and no command key takes a wildcard; send a command to one device's or "
                "bus's cmd key. Nothing was sent"
            )
            self._answer(query, lambda: settled(error_reply(refused)), key)
            return
        self._answer(query, lambda: settled(self.api.info()), key)

    def _trajectory_query(self, query: zenoh.Query) -> Routed | None:
        """Only on this gateway's own key: a get on ``busgate/*/trajectory`` names no gateway,
        and a play it carried would move every gateway with those device names. Refused,
        once by each gateway it reaches (rather than left to wait out its timeout), unless
        it reaches the info key too (``**``: the info answers it, rule 5)."""
        key = self.keys.trajectory(self.name)
        if str(query.key_expr) != key:
            if self._reaches_info(query.key_expr):
                query.drop()
                return None
            self._refuse_wildcard(
                query,
                f"{shown(str(query.key_expr))} has a wildcard: a trajectory is sent to one "
                f"gateway's own key (such as {key}). Nothing was played",
                key,
            )
            return None
        return _routed(key, query, self.submit_trajectory, MAX_TRAJECTORY_PAYLOAD)

    def _command_puts(self, room: str) -> Callable[[zenoh.Sample], None]:
        """The handler of the puts on ``<room>/<name>/cmd`` (a device's, a base's): each
        command carried out without a reply (``busgate send --put``), its refusal an event."""

        def on_put(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            name = self._named(key, room, "cmd")
            if name is None:
                log.debug("put on %s names no %s: dropped", key, ROOM_NOUNS[room])
                return
            payload = self._put_payload(name, key, sample)
            if payload is None:
                return
            command = self.api.command if room == "dev" else self.bases.command
            done = command(name, payload)
            done.add_done_callback(lambda end: self._report_put(name, key, payload, end.result()))

        return on_put

    def _take_what_came_before(self) -> None:
        """What still waits for its intake when an e-stop came was put before it (rule 6):
        commands refused ``estopped`` (on the loop's thread), puts dropped."""
        refused: list[tuple[Route, zenoh.Query]] = []
        dropped = 0
        for intake, route in self._before_estop:
            waiting = intake.take_waiting()
            if route is None:
                dropped += len(waiting)
            else:
                refused.extend((route, query) for query in waiting)
        if refused:
            self.call_soon(self._refuse_before_estop, refused)
        if dropped:
            log.info("e-stop: %d puts that came before it dropped, never carried out", dropped)
        for forget in self.at_estop:
            forget()

    def _refuse_before_estop(self, refused: list[tuple[Route, zenoh.Query]]) -> None:
        reply = error_reply(cancelled_by_estop())
        for route, query in refused:
            routed = route(query)
            if routed is not None:
                key, payload, _ = routed
                self._answer(query, lambda: settled(reply), key, payload)

    def _on_follow(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        device = self._named(key, "dev", "follow")
        if device is None:
            log.debug("follow target on %s names no device: dropped", key)
            return
        payload = self._put_payload(device, key, sample)
        if payload is None:
            return
        refused = self.api.follow(device, payload)
        self._report_put(device, key, payload, refused)

    def _on_estop_or_reset(self, sample: zenoh.Sample) -> None:
        """The e-stop and its reset, on one subscriber: zenoh runs each subscriber's callbacks
        on a thread of its own, so that two would lose the order of a reset and an e-stop put
        one after the other (which zenoh keeps on the wire, and the SDK promises). A put whose
        key reaches the e-stop (``**``, ``busgate/*/estop``) is an e-stop, never a reset."""
        if sample.key_expr.intersects(self._estop_key):
            self._on_estop(sample)
        else:
            self._on_estop_reset(sample)

    def _on_estop(self, sample: zenoh.Sample) -> None:
        came = now()  # when it came, for the recorder: its frames may go before it is told
        stopped = self.api.stop_every_bus()  # first: the payload only names its sender
        try:
            payload = _taken(sample.payload)
        except RefusedError:  # too large to name a client: it names none
            payload = b""
        self._told_estop(stopped, estop_sender(payload), str(sample.key_expr))
        self.on_command(str(sample.key_expr), payload, None, came)

    def estop(self, sender: str | None, key: str) -> list[Future]:
        """Every device of the gateway stopped, ahead of everything, told as an ``estop``
        event naming where it came from (``key``); any thread."""
        return self._told_estop(self.api.stop_every_bus(), sender, key)

    def estop_reset(self, sender: str | None) -> tuple[list[Future], list[str]]:
        """Every device out of its e-stop but those another client claims, told as an
        ``estop_reset`` event (at most one every 0.1 s, as the e-stop's, ``put_reports``);
        any thread. The buses' futures, and the devices not reset."""
        reset, not_reset = self.api.reset_every_bus(sender)
        self.put_reports.estop_reset(sender, not_reset)
        return reset, not_reset

    def _told_estop(self, stopped: list[Future], sender: str | None, key: str) -> list[Future]:
        """Once every bus has the e-stop: what was put or got before it and still waits taken
        (rule 6), its log line and ``estop`` event (at most one every 0.1 s, ``put_reports``)."""
        self._take_what_came_before()
        self.put_reports.estop(key, sender)
        return stopped

    def _tell_put(self, event: DeviceEvent) -> None:
        """A refused put's, an e-stop's or a reset's event, told (the last two with their log
        line)."""
        if event.type in TOLD_LINES:
            fields = event.fields
            log_told(
                event.type,
                fields.get("client"),
                fields.get("suppressed", 0),
                fields.get("not_reset", ()),
            )
        self.events.append(event)

    def submit_trajectory(
        self, payload: bytes, came_under: int | None = None, limit: int = MAX_TRAJECTORY_PAYLOAD
    ) -> Future:
        """A trajectory command (``<base>/trajectory``'s payload, of at most ``limit`` bytes)
        in its lane: the reply's future. A play is refused ``estopped`` if an e-stop came after
        it was taken: ``came_under`` is the count of e-stops then, by default the one this
        thread's intake took it under (``intake`` rule 5)."""
        if came_under is None:
            came_under = estops_when_taken(self.api.estops)
        return self._trajectory_lanes.submit(payload, came_under, limit=limit)

    def _on_estop_reset(self, sample: zenoh.Sample) -> None:
        """Only on this gateway's own reset key: a put on ``**`` or ``busgate/*/estop/**``
        reaches the e-stop too, and a reset must never ride along with a stop. Unlike the
        e-stop, which takes any payload, a reset is carried out only on an empty payload or
        an object with nothing but a ``client``, if any, that is a client id: else it is
        refused, told as a ``command_refused`` event, and nothing is reset."""
        key = str(sample.key_expr)
        if key != self.keys.estop_reset(self.name):
            log.debug("e-stop reset on %s ignored: a reset names its gateway's key", key)
            return
        payload = b""  # what is recorded of one too large to read
        try:
            payload = _taken(sample.payload)
            sender = reset_sender(payload)
        except RefusedError as refusal:
            refused = error_reply(refusal)
            self.put_reports.refused("*", refused["error"])  # the whole gateway's
            self.on_command(key, payload, refused, None)  # the flight recorder keeps refusals
            return
        self.estop_reset(sender)
        self.on_command(key, payload, None, None)

    def _on_client(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.call_soon(self._client_left, str(sample.key_expr).split("/")[-1])

    def _client_left(self, client: str) -> None:
        """The loop's thread: the client's trajectories end ``client gone`` first, in the same
        callback, so that no round of the loop sees them under claims already released (and
        aborts them ``claim lost`` instead); then its claims, streams and speeds go."""
        self.trajectories.client_left(client)
        self.bases.client_left(client)
        self.api.client_left(client)

    def _answer(
        self,
        query: zenoh.Query,
        handle: Callable[[], Future],
        key: str,
        payload: bytes | None = None,
    ) -> None:
        """Reply on ``key`` (concrete, even when the query had wildcards), on the loop's
        thread, once the future ``handle`` returns is done (or too late): exactly once. A
        command's ``payload`` goes to ``on_command`` with its reply."""
        loop = self._loop
        assert loop is not None
        replied: Future[bool] = Future()
        asked = now()
        guard: list[asyncio.TimerHandle] = []

        def send(reply: dict[str, Any]) -> None:
            if replied.done():
                return
            replied.set_result(True)
            for timer in guard:  # answered: the query is not kept for the guard's 10 s
                timer.cancel()
            # Dated before the reply goes: what its client does next (an e-stop put at once)
            # comes later in the flight recorder too, not before it (a race CI met).
            answered = now()
            try:
                query.reply(key, message_json(reply))
            finally:
                query.drop()
                self.on_latency(now() - asked)
                if payload is not None:
                    self.on_command(key, payload, reply, answered)

        try:
            result = handle()
        except Exception as exc:  # the API answers everything; this is the last net
            log.exception("query on %s failed", key)
            self.call_soon(send, error_reply(exc))
            return

        def too_late() -> None:
            if result.cancel():  # not carried out, and now never will be
                send(
                    error_reply(
                        RefusedError(
                            "internal", "no answer from the bus in time; the command was withdrawn"
                        )
                    )
                )

        def arm_guard() -> None:
            if not replied.done():
                guard.append(loop.call_later(REPLY_TIMEOUT_S, too_late))

        def done(finished: Future) -> None:
            if not finished.cancelled():
                self.call_soon(send, finished.result())

        result.add_done_callback(done)
        loop.call_soon_threadsafe(arm_guard)

    def _put_payload(self, name: str, key: str, sample: zenoh.Sample) -> bytes | None:
        """The payload of a put on ``key`` (of the device or base ``name``), copied out of
        zenoh only when the key takes so many bytes (``_routed``); else ``None``, refused
        ``too_large`` and told as any refused put is."""
        try:
            return _taken(sample.payload)
        except RefusedError as refused:
            self._report_put(name, key, b"", error_reply(refused))
            return None

    def _report_put(
        self, device: str, key: str, payload: bytes, reply: dict[str, Any] | None
    ) -> None:
        """A put's outcome (``None``: a follow target taken): a refusal is an event."""
        if reply is not None and not reply.get("ok"):
            self.put_reports.refused(device, reply["error"])
        self.on_command(key, payload, reply, None)

    def call_soon(self, function, *args: Any) -> None:
        """``function(*args)`` on the loop's thread, from any thread (rule 1's hand-over)."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(function, *args)

    # -- publishing (the loop's thread) -----------------------------------------------------

    def publish_states(self) -> None:
        """Every state the bus threads made since the last round, in order: a round that
        comes late publishes a backlog, it does not skip what a device reported."""
        states, keys, tokens = self.states, self._state_keys, self._device_tokens
        while states:
            device, state = states.popleft()
            key = keys.get(device)
            if key is None:
                key = keys[device] = self.keys.device(self.name, device, "state")
            self._put(key, state)
            online = bool(state.get("online"))
            if online is not (device in tokens):  # its token comes or goes
                self._track_liveliness(device, online)
            self.joints.take(device, state)
            self.bases.take_state(device, state)
        joints = self.joints.due(now(), time.time())
        if joints is not None:
            self._put(self.keys.joints(self.name), joints)
            self.on_joints(joints)

    def publish_events(self) -> None:
        while self.events:
            event = self.events.popleft()
            body = {"ts": time.time(), "device": event.device, "type": event.type, **event.fields}
            if event.device in self.api.devices:
                self._put(self.keys.device(self.name, event.device, "event"), body)
            self._put(self.keys.events(self.name), body)

    def publish_stats(self) -> None:
        for bus, runner in self.runners.items():
            stats = asdict(runner.statistics())
            body = {"ts": time.time(), "bus": bus, "up": runner.owner.is_open, **stats}
            self._put(self.keys.bus(self.name, bus, "stats"), body)

    def _put(self, key: str, value: dict[str, Any]) -> None:
        publisher = self._publishers.get(key)
        if publisher is not None:
            data = message_json(value)
            publisher.put(data)
            self.on_published(key, value, data)

    def _odometry(self, name: str, odometry: dict[str, Any]) -> None:
        self._put(self.keys.base(self.name, name, "odom"), odometry)
        self.on_odometry(name, odometry)

    def _put_any(self, key: str, value: dict[str, Any]) -> None:
        """A put on a key with no declared publisher (a trajectory's feedback)."""
        if self._session is not None:
            data = message_json(value)
            self._session.put(key, data, congestion_control=zenoh.CongestionControl.DROP)
            self.on_published(key, value, data)

    def _track_liveliness(self, device: str, online: bool) -> None:
        if self._session is None:
            return
        if online and device not in self._device_tokens:
            key = self.keys.device(self.name, device, "alive")
            self._device_tokens[device] = self._session.liveliness().declare_token(key)
        elif not online and device in self._device_tokens:
            self._device_tokens.pop(device).undeclare()


def ignored(*args: Any) -> None:
    """A hook (``on_published``, ``on_command``…) nothing listens to."""


def _session_named(session: zenoh.Session, zid: str) -> str:
    """Another zenoh session as a log line names it: its id, and where it is linked with
    ``session`` when it is directly (not through a router)."""
    links = [link.dst for link in session.info.links() if str(link.zid) == zid]
    return f"zenoh session {zid}" + (f" at {', '.join(links)}" if links else "")


def _routed(
    key: str, query: zenoh.Query, carry_out: Callable[[bytes], Future], limit: int = MAX_PAYLOAD
) -> Routed:
    """``query`` to carry out on ``key``: its payload copied out of zenoh only when the key
    takes so many bytes, else refused ``too_large`` by its size alone. A copy waits for the
    interpreter's lock, which the bus threads hold in turns of up to 5 ms: a flood of
    2 MiB gets was handled some 300 a second, fewer than four clients sent, and zenoh's ring
    held what waited (3.7 GB in 25 s); refused unread, they are handled as fast as they come
    (rule 6)."""
    try:
        payload = _taken(query.payload, limit)
    except RefusedError as exc:
        refused = error_reply(exc)
        return key, b"", lambda: settled(refused)
    return key, payload, lambda: carry_out(payload)


def _taken(payload: zenoh.ZBytes | None, limit: int = MAX_PAYLOAD) -> bytes:
    """``payload`` copied out of zenoh when it is at most ``limit`` bytes (none: empty);
    past it refused ``too_large`` by its size, never copied (``_routed``)."""
    if payload is None:
        return b""
    if len(payload) > limit:
        raise too_large(len(payload), limit)
    return payload.to_bytes()
