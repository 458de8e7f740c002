"""The soak: every device kind streaming and polling for ten minutes, four clients,
faults injected on every serial line. What must hold at the end: no UART gap under the bus's
gap, no follow interval under its period, every get answered, and the daemon's memory, file
descriptors and threads flat.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off: the simulators and the daemon (``busgate run``) as child processes,
the four clients as threads here, each with its own zenoh session.

    .venv/bin/python tests/benchmarks/soak.py --seconds 600

The gateway: 3 Inspire LA at 921600 baud (follow 10 ms, polls 20 Hz), 2 DS servos at 1 Mbaud
(follow 20 ms, polls 20 Hz), a ZLAC706 on RS232 (velocity follow 20 ms, polls 10 Hz) and two
on CAN behind the simulated SLCAN adapter (velocity follow 20 ms, heartbeats every 20 ms).
The clients: one streams the LA and DS positions, one the ZLAC706 speeds, one sends status
gets in a loop, one watches telemetry, events and bus statistics and every few seconds claims
the LA actuators, moves them together (``group_move``) and releases them (the position
stream's puts are refused meanwhile: counted, not a failure).

Figures: the daemon's RSS, open fds and threads after the warm-up and at the end (a line a
minute on stderr in between) and its CPU; gateway side, the buses' statistics as published
(counters over the measured window, the smallest follow error over every snapshot); device
side, each serial simulator's wire record over the window (``wire_analysis``); every get's
outcome by op and code (``busy`` and ``device_timeout`` are answers; nothing back within the
bridge's own reply timeout is a lost reply). The exit status is 1 when a check fails.

Gaps and follow intervals are judged on the gateway's side: it times its own writes and reads,
and a tick is due a period after the previous one started, so its figures are exact. The
simulators' records are printed beside them but cannot decide: on two shared cores, three
simulators reading ptys see frames late by their wake-up, and a stalled one reads several at
once and dates them by its model of the line, so device-side intervals scatter both ways
around the period. Busy polling (``--sim-busy-poll-ms``, as ``busgate bench`` uses for its one
simulator) does not help here: three spinning simulators take both cores from the gateway.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready

from busgate.client.core import Answer, answer_of
from busgate.gateway.api.bridge import REPLY_TIMEOUT_S
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import cpu_s
from busgate.gateway.drivers.families import driver_class
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import WireFigures, analyse, load_records
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.zenoh_session import session_config

BASE = "busgate/bench"  # bench_zenoh's Daemon names the gateway "bench"
FAULTS = "--bad-checksum-rate 0.02 --garbage-rate 0.02 --drop-rate 0.01"
GET_TIMEOUT_S = REPLY_TIMEOUT_S + 2  # the bridge answers "internal" itself after its timeout
POLL_GET_EVERY_S = 0.01
CLAIM_EVERY_S = 10.0
CLAIM_HOLD_S = 0.3
CAN_HEARTBEAT_MS = 20
CAN_FOLLOW_MS = 20


@dataclass(frozen=True)
class SerialLine:
    """One serial bus of the soak and its simulator (``protocol`` names both)."""

    bus: str
    protocol: str
    kind: str
    ids: tuple[int, ...]
    baudrate: int
    follow_period_ms: float
    poll_hz: float
    status: str  # the get the polling client sends its devices
    #: The frames its follow ticks are (a fresh ZLAC706 driver refuses a target until its mode
    #: is known, so the names cannot be asked of one here).
    follow_frames: tuple[str, ...]

    @property
    def devices(self) -> list[str]:
        return [f"{self.bus}-{i}" for i in self.ids]  # as bench_zenoh's serial_bus names them

    @property
    def gap_s(self) -> float:
        return PROTOCOLS[self.protocol].timing.default_gap_s  # the bus config sets no min_gap_ms


LINES = (
    SerialLine("la", "inspire_la", "inspire_la", (1, 2, 3), 921_600, 10, 20, '{"op":"status"}',
               ("FollowCommand", "GroupFollowCommand")),
    SerialLine("ds", "ds_servo", "ds_servo", (1, 2), 1_000_000, 20, 20, '{"op":"ping"}',
               ("SyncWrite",)),
    SerialLine("rs232", "zlac706_rs232", "zlac706", (1,), 115_200, 20, 10, '{"op":"monitor"}',
               ("Write",)),
)
CAN_IDS = (1, 2)
CAN_DEVICES = [f"can-{i}" for i in CAN_IDS]
#: Every device and its protocol.
PROTOCOL_OF = {**{d: line.protocol for line in LINES for d in line.devices},
               **dict.fromkeys(CAN_DEVICES, "zlac706_can")}
#: Every device's driver class: what makes it ready to follow, and its follow samples.
DRIVER_OF = {device: driver_class(PROTOCOLS[protocol]) for device, protocol in PROTOCOL_OF.items()}


def can_bus(port: str) -> str:
    text = ('[[buses]]\nname = "can"\ntransport = "can"\ninterface = "slcan"\n'
            f'channel = "{port}"\noptions = {{ sleep_after_open = 0 }}\n')
    for ident, name in zip(CAN_IDS, CAN_DEVICES, strict=True):
        text += (f'[[buses.devices]]\nname = "{name}"\nkind = "zlac706"\n'
                 f'id = {ident}\nfollow_period_ms = {CAN_FOLLOW_MS}\n'
                 f'heartbeat_ms = {CAN_HEARTBEAT_MS}\n')
    return text


def gateway_buses(ports: dict[str, str]) -> str:
    text = "".join(serial_bus(line.bus, ports[line.bus], line.kind, list(line.ids),
                              line.baudrate, poll_hz=line.poll_hz,
                              follow_period_ms=line.follow_period_ms) for line in LINES)
    return text + can_bus(ports["can"])


# -- the clients ----------------------------------------------------------------------------


class GetTally:
    """Every get any client sent, and what came back, by op (thread-safe)."""

    def __init__(self) -> None:
        self.outcomes: Counter[tuple[str, str]] = Counter()  # (op, ok | error code | lost)
        self.seconds: list[float] = []
        self._lock = threading.Lock()

    def ask(self, session: zenoh.Session, key: str, payload: str) -> None:
        """Send one get and count its outcome: ``ok``, the error code, or ``lost``."""
        asked = now()
        replies = session.get(key, payload=payload, timeout=GET_TIMEOUT_S)
        answers = [answer for reply in replies if (answer := answer_of(reply)) is not None]
        took = now() - asked
        code = _code(answers[0] if answers else None)
        with self._lock:
            self.outcomes[json.loads(payload)["op"], code] += 1
            self.seconds.append(took)

    def count(self, code: str | None = None) -> int:
        """Gets with this outcome (all gets when ``None``)."""
        with self._lock:
            return sum(n for (_, c), n in self.outcomes.items() if code in (None, c))

    def by_op(self) -> dict[str, dict[str, int]]:
        table: dict[str, dict[str, int]] = {}
        with self._lock:
            for (op, code), n in sorted(self.outcomes.items()):
                table.setdefault(op, {})[code] = n
        return table


def _code(answer: Answer | None) -> str:
    if answer is None:
        return "lost"
    return "ok" if answer.ok else str(answer.error.get("code"))


class Client(threading.Thread):
    """A client in a thread with its own zenoh session and liveliness token."""

    def __init__(self, name: str, endpoint: str, tally: GetTally, stop: threading.Event) -> None:
        super().__init__(name=name, daemon=True)
        self.endpoint, self.tally, self.stop = endpoint, tally, stop
        self.error: BaseException | None = None

    def run(self) -> None:
        session = zenoh.open(session_config(connect=[self.endpoint]))
        token = session.liveliness().declare_token(f"busgate/clients/{self.name}")
        try:
            self.work(session)
        except BaseException as exc:  # reported by the main thread
            self.error = exc
            self.stop.set()
        finally:
            token.undeclare()
            session.close()

    def work(self, session: zenoh.Session) -> None:
        raise NotImplementedError


class Streamer(Client):
    """Prepares its devices (enable, torque on, velocity mode) with gets, then puts a new
    follow target for each twice per its shortest period, as ``busgate bench`` does."""

    def __init__(self, *args: Any, devices: list[str], period_ms: float) -> None:
        super().__init__(*args)
        self.devices, self.step_s = devices, period_ms / 2000

    def work(self, session: zenoh.Session) -> None:
        for device in self.devices:
            for command in DRIVER_OF[device].follow_preparation:
                self.tally.ask(session, f"{BASE}/dev/{device}/cmd", command)
        publishers = [(session.declare_publisher(f"{BASE}/dev/{d}/follow"),
                       DRIVER_OF[d].follow_sample, i) for i, d in enumerate(self.devices)]
        while not self.stop.wait(self.step_s):
            moment = now()
            for publisher, trajectory, index in publishers:
                publisher.put(json.dumps(trajectory(moment, index)))


class Poller(Client):
    """Status gets round the serial devices (CAN has nothing to read: heartbeats report)."""

    def work(self, session: zenoh.Session) -> None:
        asks = itertools.cycle([(d, line.status) for line in LINES for d in line.devices])
        while not self.stop.wait(POLL_GET_EVERY_S):
            device, status = next(asks)
            self.tally.ask(session, f"{BASE}/dev/{device}/cmd", status)


@dataclass
class Watched:
    """What the watcher has seen (written on zenoh's threads, read at the end)."""

    states: Counter[str] = field(default_factory=Counter)
    offline: Counter[str] = field(default_factory=Counter)
    stale: Counter[str] = field(default_factory=Counter)
    events: Counter[str] = field(default_factory=Counter)
    stats: dict[str, dict[str, Any]] = field(default_factory=dict)
    follow_error_min_s: dict[str, float] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def state(self, sample: zenoh.Sample) -> None:
        state = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.states[state["device"]] += 1
            self.offline[state["device"]] += not state["online"]
            self.stale[state["device"]] += state["stale"]

    def event(self, sample: zenoh.Sample) -> None:
        event = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.events[f"{event['type']}:{event.get('code', '')}".rstrip(":")] += 1

    def bus_stats(self, sample: zenoh.Sample) -> None:
        stats = json.loads(sample.payload.to_bytes())
        bus, lowest = stats["bus"], stats["follow_error_min_s"]  # of the last 10,000 intervals
        with self.lock:
            self.stats[bus] = stats
            if lowest is not None:
                self.follow_error_min_s[bus] = min(self.follow_error_min_s.get(bus, lowest),
                                                   lowest)


class Watcher(Client):
    """Telemetry, events and bus statistics; every ``CLAIM_EVERY_S`` a claimed group move."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.seen = Watched()

    def work(self, session: zenoh.Session) -> None:
        subscribers = [session.declare_subscriber(f"{BASE}/dev/*/state", self.seen.state),
                       session.declare_subscriber(f"{BASE}/events", self.seen.event),
                       session.declare_subscriber(f"{BASE}/bus/*/stats", self.seen.bus_stats)]
        for round_ in itertools.count():
            if self.stop.wait(CLAIM_EVERY_S):
                break
            self.claimed_group_move(session, position=300 if round_ % 2 else 1700)
        for subscriber in subscribers:
            subscriber.undeclare()

    def claimed_group_move(self, session: zenoh.Session, position: int) -> None:
        devices = LINES[0].devices
        for device in devices:
            claim = {"op": "claim", "client": self.name, "ttl_s": 5}
            self.tally.ask(session, f"{BASE}/dev/{device}/cmd", json.dumps(claim))
        move = {"op": "group_move", "client": self.name,
                "targets": [{"device": d, "position": position} for d in devices]}
        self.tally.ask(session, f"{BASE}/bus/{LINES[0].bus}/cmd", json.dumps(move))
        time.sleep(CLAIM_HOLD_S)
        for device in devices:
            release = {"op": "release", "client": self.name}
            self.tally.ask(session, f"{BASE}/dev/{device}/cmd", json.dumps(release))


# -- the daemon as the kernel sees it ---------------------------------------------------------


@dataclass(frozen=True)
class ProcessFigures:
    rss_kib: int
    fds: int
    threads: int
    cpu_s: float
    at: float

    @classmethod
    def of(cls, pid: int) -> ProcessFigures:
        status = dict(line.split(":", 1) for line in
                      Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
        return cls(rss_kib=int(status["VmRSS"].split()[0]), threads=int(status["Threads"]),
                   fds=len(os.listdir(f"/proc/{pid}/fd")), cpu_s=cpu_s(f"/proc/{pid}/stat"),
                   at=now())

    def line(self, since: ProcessFigures) -> str:
        cpu = 100 * (self.cpu_s - since.cpu_s) / max(self.at - since.at, 1e-9)
        return (f"RSS {self.rss_kib / 1024:.1f} MiB, {self.fds} fds, {self.threads} threads, "
                f"CPU {cpu:.1f} % of a core")


# -- the run ------------------------------------------------------------------------------------


def start_simulators(stack: contextlib.ExitStack, scratch: Path, args) -> dict[str, str]:
    """The serial simulators (faults, wire records) and the SLCAN one; their ports by bus."""
    quiet = ["--busy-poll-ms", str(args.sim_busy_poll_ms)]
    ports = {}
    for line in LINES:
        sim_args = ["--ids", ",".join(map(str, line.ids)), "--baudrate", str(line.baudrate),
                    "--record", str(scratch / f"{line.bus}.jsonl"), *quiet, *args.faults.split()]
        ports[line.bus] = stack.enter_context(SimProcess(line.protocol, sim_args)).port
    can_args = ["--ids", ",".join(map(str, CAN_IDS)),
                "--heartbeat-ms", str(CAN_HEARTBEAT_MS)]
    ports["can"] = stack.enter_context(SimProcess("zlac706_can", can_args)).port
    return ports


def start_clients(endpoint: str, tally: GetTally, stop: threading.Event) -> list[Client]:
    positions = [d for line in LINES[:2] for d in line.devices]
    speeds = [*LINES[2].devices, *CAN_DEVICES]
    clients = [
        Streamer("soak-positions", endpoint, tally, stop, devices=positions, period_ms=10),
        Streamer("soak-speeds", endpoint, tally, stop, devices=speeds, period_ms=20),
        Poller("soak-poller", endpoint, tally, stop),
        Watcher("soak-watcher", endpoint, tally, stop),
    ]
    for client in clients:
        client.start()
    return clients


def soak(daemon: Daemon, clients: list[Client], tally: GetTally, args) -> dict[str, Any]:
    """Warm up, take the start figures, print a line a minute, take the end figures."""
    stop = clients[0].stop
    watcher = clients[-1]
    stop.wait(args.warmup)
    first = ProcessFigures.of(daemon.process.pid)
    stats_at_start = dict(watcher.seen.stats)
    end = first.at + args.seconds
    while not stop.wait(max(0.0, min(args.every, end - now()))) and now() < end:
        figures = ProcessFigures.of(daemon.process.pid)
        sent, lost = tally.count(), tally.count("lost")
        print(f"[{figures.at - first.at:5.0f} s] {figures.line(first)}; gets {sent - lost}/{sent} "
              f"answered; {sum(watcher.seen.states.values())} states", file=sys.stderr)
    last = ProcessFigures.of(daemon.process.pid)
    return {"first": first, "last": last, "stats_at_start": stats_at_start,
            "stats_at_end": dict(watcher.seen.stats), "window": (first.at, last.at)}


def device_side(scratch: Path, window: tuple[float, float]) -> dict[str, WireFigures]:
    figures = {}
    for line in LINES:
        records = [r for r in load_records(scratch / f"{line.bus}.jsonl")
                   if window[0] <= r.start <= window[1]]
        figures[line.bus] = analyse(records, min_gap_s=line.gap_s,
                                    follow_frames=line.follow_frames,
                                    follow_period_s=line.follow_period_ms / 1000)
    return figures


def run(args) -> int:
    with contextlib.ExitStack() as scratch_dir:
        scratch = Path(args.records or scratch_dir.enter_context(tempfile.TemporaryDirectory()))
        scratch.mkdir(parents=True, exist_ok=True)
        return run_in(scratch, args)


def run_in(scratch: Path, args) -> int:
    tally, stop = GetTally(), threading.Event()
    with contextlib.ExitStack() as sims:
        ports = start_simulators(sims, scratch, args)
        endpoint = free_endpoint()
        daemon = Daemon(scratch, endpoint, gateway_buses(ports))
        try:
            with zenoh.open(session_config(connect=[endpoint])) as probe:
                wait_ready(probe)
            clients = start_clients(endpoint, tally, stop)
            try:
                measured = soak(daemon, clients, tally, args)
            finally:
                stop.set()
                for client in clients:
                    client.join(GET_TIMEOUT_S + 5)
        finally:
            daemon.stop()
    # the simulators have stopped, so their records are complete
    sizes = {line.bus: (scratch / f"{line.bus}.jsonl").stat().st_size for line in LINES}
    wire = device_side(scratch, measured["window"])
    errors = [f"{c.name}: {c.error!r}" for c in clients if c.error is not None]
    return report(args, measured, wire, tally, clients[-1].seen, sizes, errors)


# -- the report -----------------------------------------------------------------------------


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.3f}"


def _delta(measured: dict[str, Any], bus: str, name: str) -> int:
    before = measured["stats_at_start"].get(bus, {}).get(name, 0)
    return measured["stats_at_end"].get(bus, {}).get(name, 0) - before


WIRE_NOTE = """\
Device side: times are when each simulator read a frame off its pty, late by its own wake-up
(a stalled simulator reads several frames at once, then dates them by its model of the line),
so this side shows read jitter both ways and is not part of the verdict."""


def wire_table(wire: dict[str, WireFigures]) -> list[str]:
    lines = ["| bus (device side) | follow frames | under the period | smallest interval ms "
             "| error p50 / p99 ms | gap ms | gaps under it (after reply / after silent frame) "
             "| smallest gap ms (after reply / silent) | unresolved |",
             "| --- " * 9 + "|"]
    for line in LINES:
        w = wire[line.bus]
        lines.append(
            f"| {line.bus} | {w.follow_frames} | {w.follow_intervals_under_period} | "
            f"{_ms(w.smallest_follow_interval_s)} | {_ms(w.follow_error_p50_s)} / "
            f"{_ms(w.follow_error_p99_s)} | {line.gap_s * 1000:g} | "
            f"{w.gaps_after_reply_below_minimum} / {w.gaps_after_silent_frame_below_minimum} | "
            f"{_ms(w.smallest_gap_after_reply_s)} / {_ms(w.smallest_gap_after_silent_frame_s)} "
            f"| {w.unresolved} |")
    return lines


STAT_COUNTERS = ("follow_intervals", "timeouts", "retries", "checksum_errors", "late_replies",
                 "skipped_polls", "busy_commands", "reconnects")


def stats_table(measured: dict[str, Any], seen: Watched) -> list[str]:
    lines = ["| bus (gateway side) | follow error min ms | p99 ms (last 10,000) | smallest gap ms "
             "| " + " | ".join(name.replace("_", " ") for name in STAT_COUNTERS) + " |",
             "| --- " * (4 + len(STAT_COUNTERS)) + "|"]
    for bus, stats in sorted(measured["stats_at_end"].items()):
        counters = " | ".join(str(_delta(measured, bus, name)) for name in STAT_COUNTERS)
        lines.append(f"| {bus} | {_ms(seen.follow_error_min_s.get(bus))} | "
                     f"{_ms(stats['follow_error_p99_s'])} | {_ms(stats['smallest_gap_s'])} | "
                     f"{counters} |")
    return lines


def checks(measured, wire, tally: GetTally, seen: Watched, errors: list[str]) -> list[str]:
    """What failed (empty: the soak passed). Gaps and follow intervals are judged on the
    gateway's side, which times its own writes and reads exactly (see ``WIRE_NOTE``)."""
    first, last = measured["first"], measured["last"]
    failed = list(errors)
    for line in LINES:
        smallest = measured["stats_at_end"].get(line.bus, {}).get("smallest_gap_s")
        if smallest is None or smallest < line.gap_s:
            failed.append(f"{line.bus}: a gap under {line.gap_s * 1000:g} ms (or none measured)")
        if not wire[line.bus].follow_frames:
            failed.append(f"{line.bus}: no follow frame in the simulator's record")
    for bus in [line.bus for line in LINES] + ["can"]:
        if seen.follow_error_min_s.get(bus, -1) < 0 or not _delta(measured, bus,
                                                                   "follow_intervals"):
            failed.append(f"{bus}: a follow interval under the period (or none)")
    if tally.count("lost") or tally.count("internal"):
        failed.append("gets without an answer from the bus")
    if last.fds > first.fds or last.threads > first.threads:
        failed.append("the daemon has more fds or threads than after the warm-up")
    if last.rss_kib > first.rss_kib * 1.05:
        failed.append("the daemon's RSS grew by more than 5 %")
    failed += [f"{d}: no telemetry" for d in PROTOCOL_OF if not seen.states[d]]
    return failed


def report(args, measured, wire, tally: GetTally, seen: Watched, sizes: dict[str, int],
           errors: list[str]) -> int:
    first, last = measured["first"], measured["last"]
    seconds = sorted(tally.seconds)
    print(f"busgate soak: {last.at - first.at:.0f} s after a {args.warmup:g} s warm-up; "
          f"faults on every serial simulator: {args.faults}; simulators busy-poll "
          f"{args.sim_busy_poll_ms:g} ms")
    print("\n| daemon | after the warm-up | at the end |\n| --- | --- | --- |")
    print(f"| RSS | {first.rss_kib / 1024:.1f} MiB | {last.rss_kib / 1024:.1f} MiB |")
    print(f"| open fds | {first.fds} | {last.fds} |\n| threads | {first.threads} | "
          f"{last.threads} |")
    print(f"\ndaemon CPU over the window: {last.line(first).split('CPU ')[1]}")
    print(f"gets: {tally.count()} sent, {tally.count('lost')} lost; by op and outcome "
          f"{tally.by_op()}; reply time p50 "
          f"{_ms(percentile(seconds, 0.5))} ms, p99 {_ms(percentile(seconds, 0.99))} ms, max "
          f"{_ms(seconds[-1] if seconds else None)} ms")
    print(f"telemetry: {sum(seen.states.values())} states; offline samples "
          f"{dict(+seen.offline) or 0}; stale samples {dict(+seen.stale) or 0}")
    print(f"events: {dict(sorted(seen.events.items()))}")
    print("wire records: " + ", ".join(f"{bus} {size / 1e6:.1f} MB"
                                       for bus, size in sizes.items()))
    print("\n" + "\n".join(wire_table(wire)) + "\n\n" + WIRE_NOTE)
    print("\n" + "\n".join(stats_table(measured, seen)))
    failed = checks(measured, wire, tally, seen, errors)
    print("\n" + ("PASS" if not failed else "FAIL:\n  " + "\n  ".join(failed)))
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="measured time (600)")
    parser.add_argument("--warmup", type=float, default=30.0, help="before measuring (30)")
    parser.add_argument("--every", type=float, default=60.0, help="progress line period (60)")
    parser.add_argument("--faults", default=FAULTS, help=f"serial sim fault flags ({FAULTS})")
    parser.add_argument("--records", help="keep the config and wire records in this directory "
                        "(default: a temporary one, removed at the end)")
    parser.add_argument("--sim-busy-poll-ms", type=float, default=0.0,
                        help="the serial simulators' busy polling after each frame (0: three "
                        "spinning simulators would starve the gateway on two cores)")
    return run(parser.parse_args())


if __name__ == "__main__":
    sys.exit(main())
