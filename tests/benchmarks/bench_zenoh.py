"""The zenoh API's figures: command latency to the wire, e-stop latency, telemetry CPU.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off: the simulators and the daemon (``busgate run``) as child processes,
the client here. Clocks are comparable across processes (perf_counter is CLOCK_MONOTONIC).

    .venv/bin/python tests/benchmarks/bench_zenoh.py

1. A client's get on a device's cmd key → its frame on the wire (the simulator's arrival
   time), p50/p99, beside a bare zenoh put → subscriber hop between two sessions measured in
   the same run; each get on a line idle for 3 ms (one sooner waits for the 1 ms gap).
2. An e-stop put → the e-stop frame on every bus, while every bus streams and polls (3 LA
   actuators at 921600 baud, 2 DS servos at 1 Mbaud, each polled at 50 Hz): p99.
3. 20 devices with 100 Hz telemetry (ZLAC706 heartbeats every 10 ms, four CAN buses of five,
   the daemon in this process): the daemon's CPU. Twice: with the simulators in this process
   on python-can's ``virtual`` bus (their threads' CPU subtracted, their turns on the
   interpreter not), and with each bus's simulator in a process of its own behind
   ``unix_can.py`` (SocketCAN's frames over a Unix socket, standing in for SocketCAN, which
   this host lacks).
4. The same 20 devices apart: how far each state's ``ts`` is from its device's state before
   (``heartbeat_steps_apart``), where the heartbeats come every 10 ms, and how old each state
   is when a subscriber takes it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import unix_can
import zenoh
from usage import arguments

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import cpu_s, thread_cpu_s
from busgate.gateway.service.daemon import serve
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import load_records
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import parse_config
from busgate.schemas.zenoh_session import session_config


def free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def ms(values: list[float], q: float) -> float:
    return round(percentile(sorted(values), q) * 1000, 3)


class Daemon:
    """``busgate run`` on a config written from ``buses`` (TOML text), with ``gateway``'s
    lines in its ``[gateway]`` table besides its name (by default every bus in the daemon's
    process, ``workers = 1``, as this directory's figures were measured); its log to
    ``stderr`` (default: ours)."""

    def __init__(self, scratch: Path, endpoint: str, buses: str, name: str = "bench",
                 gateway: str = "workers = 1\n", stderr=None) -> None:
        config = scratch / f"{name}.toml"
        config.write_text(f'[gateway]\nname = "{name}"\n{gateway}[zenoh]\nlisten = ["{endpoint}"]\n'
                          f"{buses}")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "busgate.gateway.cli", "run", "--config", str(config),
             "--log-level", "warning"], stderr=stderr)

    def cpu_s(self) -> float:
        return cpu_s(f"/proc/{self.process.pid}/stat")

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        self.process.wait(10)


def serial_bus(name: str, port: str, kind: str, ids: list[int], baud: int,
               bus_fields: str = "", **extra) -> str:
    """A serial bus's TOML: ``bus_fields`` (lines) on the bus, ``extra`` on each device."""
    text = f'[[buses]]\nname = "{name}"\ntransport = "serial"\nport = "{port}"\nbaudrate = {baud}\n'
    text += bus_fields
    for i in ids:
        text += f'[[buses.devices]]\nname = "{name}-{i}"\nkind = "{kind}"\nid = {i}\n'
        text += "".join(f"{k} = {v}\n" for k, v in extra.items())
    return text


def wait_ready(client: zenoh.Session, timeout: float = 20.0, gateway: str = "bench") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reply in client.get(f"busgate/{gateway}/info", timeout=1):
            if reply.ok:
                info = json.loads(reply.ok.payload.to_bytes())
                states = [d["state"] for b in info["buses"] for d in b["devices"]]
                if all(s and s["online"] for s in states):
                    return
        time.sleep(0.2)
    raise RuntimeError("the gateway's devices did not come online")


def bare_hop(samples: int = 2000) -> list[float]:
    """put → subscriber callback between two zenoh sessions on loopback."""
    endpoint = free_endpoint()
    a = zenoh.open(session_config(listen=[endpoint]))
    b = zenoh.open(session_config(connect=[endpoint]))
    hops: list[float] = []
    done = threading.Event()

    def received(sample: zenoh.Sample) -> None:
        hops.append(now() - float(sample.payload.to_bytes()))
        if len(hops) >= samples:
            done.set()

    subscriber = b.declare_subscriber("bench/hop", received)
    time.sleep(0.5)
    for _ in range(samples):
        a.put("bench/hop", repr(now()))
        time.sleep(0.002)
    done.wait(10)
    subscriber.undeclare()
    a.close()
    b.close()
    return hops


#: How long the line is left idle before each timed get (the gap is 1 ms).
IDLE_BEFORE_GET_S = 0.003


def command_to_wire(scratch: Path, samples: int = 1000) -> list[float]:
    record = scratch / "la.jsonl"
    with SimProcess("inspire_la", ["--ids", "1", "--record", str(record)]) as sim:
        endpoint = free_endpoint()
        daemon = Daemon(scratch, endpoint, serial_bus("uart0", sim.port, "inspire_la", [1],
                                                     921600, poll_hz=1))
        client = zenoh.open(session_config(connect=[endpoint]))
        try:
            wait_ready(client)
            sent: dict[str, float] = {}
            for i in range(samples):
                position = i % 2000
                wire = la.encode(la.MoveCommand(1, position, False)).hex()
                sent[wire] = now()
                payload = json.dumps({"op": "move", "position": position, "reply": False})
                list(client.get("busgate/bench/dev/uart0-1/cmd", payload=payload, timeout=2))
                # Past the 1 ms gap after the frame: a get sent sooner waits for the gap, which
                # is the UART rule at work, not the gateway's latency.
                time.sleep(IDLE_BEFORE_GET_S)
                if i % 2000 == 1999:
                    sent.clear()
        finally:
            client.close()
            daemon.stop()
    arrivals = {r.wire: r.arrived for r in load_records(record) if r.frame == "MoveCommand"}
    return [arrivals[w] - t for w, t in sent.items() if w in arrivals]


def estop_latency(scratch: Path, rounds: int = 100) -> dict[str, list[float]]:
    records = [scratch / "e1.jsonl", scratch / "e2.jsonl"]
    # The simulators sleep in select (no busy polling): two spinning simulators would take
    # both of this machine's cores from the gateway being measured.
    quiet = ["--busy-poll-ms", "0"]
    with (SimProcess("inspire_la", ["--ids", "1,2,3", "--record", str(records[0]), *quiet]) as s1,
          SimProcess("ds_servo", ["--ids", "1,2", "--record", str(records[1]),
                                  "--baudrate", "1000000", *quiet]) as s2):
        endpoint = free_endpoint()
        buses = (serial_bus("la", s1.port, "inspire_la", [1, 2, 3], 921600, poll_hz=50)
                 + serial_bus("ds", s2.port, "ds_servo", [1, 2], 1_000_000, poll_hz=50))
        daemon = Daemon(scratch, endpoint, buses)
        client = zenoh.open(session_config(connect=[endpoint]))
        puts: list[float] = []
        try:
            wait_ready(client)
            for round_ in range(rounds):
                for i in (1, 2, 3):  # keep the LA bus streaming too
                    list(client.get(f"busgate/bench/dev/la-{i}/cmd", payload='{"op":"enable"}'))
                for _ in range(10):
                    for i in (1, 2, 3):
                        client.put(f"busgate/bench/dev/la-{i}/follow",
                                   json.dumps({"position": 500 + round_}))
                    time.sleep(0.005)
                puts.append(now())
                client.put("busgate/*/estop", b"")
                time.sleep(0.05)
        finally:
            client.close()
            daemon.stop()
    is_stop = {  # LA: single control 0x23 (e-stop); DS: write 0x28 = 0 (torque off)
        "la": lambda r: r.frame == "ControlCommand" and r.wire[8:14] == "040023",
        "ds": lambda r: r.frame == "Write" and r.wire[10:14] == "2800",
    }
    stops = {name: sorted(r.arrived or r.start for r in load_records(path) if is_stop[name](r))
             for name, path in zip(is_stop, records, strict=True)}
    latencies: dict[str, list[float]] = {"every bus": [], **{name: [] for name in stops}}
    for put in puts:
        first = {name: min((t for t in times if t >= put), default=None)
                 for name, times in stops.items()}
        if None not in first.values():
            for name, arrival in first.items():
                latencies[name].append(arrival - put)
            latencies["every bus"].append(max(first.values()) - put)
    return latencies


SUBSCRIBER = """
import json, sys, time, zenoh
from busgate.schemas.zenoh_session import session_config
session = zenoh.open(session_config(connect=[sys.argv[1]]))
times = {}  # each device's states' ts, in the order they came
ages = []  # each state's age when it came: the wall clock less its ts
def take(sample):
    state = json.loads(sample.payload.to_bytes())
    ages.append(time.time() - state["ts"])
    times.setdefault(str(sample.key_expr), []).append(state["ts"])
subscriber = session.declare_subscriber("busgate/bench/dev/*/state", take)
print("ready", flush=True)
time.sleep(float(sys.argv[2]))
subscriber.undeclare()
print(sum(map(len, times.values())), flush=True)
print(json.dumps([b - a for ts in times.values() for a, b in zip(ts, ts[1:])]), flush=True)
print(json.dumps(ages), flush=True)
session.close()
"""


def telemetry_cpu(seconds: float = 10.0) -> tuple[float, float]:
    """20 ZLAC706 on four virtual CAN buses, heartbeats every 10 ms, the daemon in this
    process (python-can's virtual bus does not cross processes) and the subscriber in a child.
    The daemon's CPU is this process's minus the simulator threads'."""
    channels = [f"bench-telemetry-{os.getpid()}-{i}" for i in range(4)]
    sims = [CanSimulator(zlac706_can, [Zlac706CanDevice(n, heartbeat_ms=10) for n in range(1, 6)],
                         bus=can.Bus(interface="virtual", channel=ch)).start() for ch in channels]
    try:
        cpu, rate, _ = _daemon_run(_heartbeat_config("virtual", channels), seconds,
                                   [sim._thread.native_id for sim in sims])
        return cpu, rate
    finally:
        for sim in sims:
            sim.stop()


#: Five heartbeating ZLAC706 on a bus of ``unix_can`` (a simulator's process).
APART_SIMULATOR = """
import sys
sys.path[:0] = [sys.argv[2]]
from unix_can import UnixCanBus, listening
from busgate.codecs import zlac706_can
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
with listening(sys.argv[1]) as server:
    print("listening", flush=True)
    bus = UnixCanBus(sys.argv[1], accepted=server.accept()[0])
devices = [Zlac706CanDevice(n, heartbeat_ms=int(sys.argv[3])) for n in range(1, 6)]
simulator = CanSimulator(zlac706_can, devices, bus=bus).start()
sys.stdin.read()  # until the benchmark closes it
simulator.stop()
"""


def telemetry_cpu_apart(seconds: float = 10.0, *, buses: int = 4,
                        heartbeat_ms: int = 10) -> tuple[float, float]:
    """``telemetry_cpu`` with each bus's five ZLAC706 in a process of their own, behind a
    ``unix_can`` bus (SocketCAN's frames over a Unix socket: this host has no ``vcan``), so
    that the daemon's CPU is this process's and nothing of the simulators is in it. Fewer
    ``buses`` show what a bus adds; ``heartbeat_ms = 0``, what idle buses cost."""
    with _apart_simulators(buses, heartbeat_ms) as channels:
        config = _heartbeat_config(unix_can.INTERFACE, channels, heartbeat_ms)
        cpu, rate, _ = _daemon_run(config, seconds, [])
    return cpu, rate


def heartbeat_steps_apart(seconds: float = 10.0) -> dict[str, float]:
    """``telemetry_cpu_apart``'s states, each device's apart in time: how far each state's
    ``ts`` is from the one before of its device (the heartbeats come every 10 ms), in ms at
    p1, p50 and p99, and the share within 1 ms of 10 ms; and how old a state is when the
    subscriber takes it (its ``ts``, the heartbeat's arrival, to the subscriber's clock), in
    ms at p50 and p99."""
    with _apart_simulators(4, 10) as channels:
        _, _, (steps, ages) = _daemon_run(
            _heartbeat_config(unix_can.INTERFACE, channels), seconds, [])
    near = sum(abs(step - 0.010) <= 0.001 for step in steps) / len(steps)
    return {"p1": ms(steps, .01), "p50": ms(steps, .5), "p99": ms(steps, .99),
            "within 1 ms of 10 ms": round(near, 3), "steps": len(steps),
            "age p50": ms(ages, .5), "age p99": ms(ages, .99)}


@contextlib.contextmanager
def _apart_simulators(buses: int, heartbeat_ms: int) -> Iterator[list[str]]:
    """``buses`` buses' channels, each with five ZLAC706 simulated in a process of their own,
    heartbeating every ``heartbeat_ms`` (0: never)."""
    unix_can.register()
    channels = [f"{os.getpid()}-{i}" for i in range(buses)]
    here = str(Path(__file__).parent)
    # The daemon leaves first, and each simulator's thread ends on its closed bus: quietly.
    sims = [subprocess.Popen([sys.executable, "-c", APART_SIMULATOR, ch, here, str(heartbeat_ms)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True)
            for ch in channels]
    try:
        for sim in sims:
            sim.stdout.readline()  # listening
        yield channels
    finally:
        for sim in sims:
            sim.stdin.close()
            try:
                sim.wait(10)
            except subprocess.TimeoutExpired:
                sim.kill()


def _heartbeat_config(interface: str, channels: list[str], heartbeat_ms: int = 10):
    """Every bus in the daemon's process (``workers = 1``): its CPU is this process's, and the
    stand-in for SocketCAN is registered here only. No stream runs; a 50 ms follow period
    keeps five wheels' worst case inside the bus, so the daemon warns of nothing. With
    ``heartbeat_ms`` 0 the wheels are told to expect none."""
    heartbeat = {"heartbeat_ms": heartbeat_ms} if heartbeat_ms else {}
    return parse_config({
        "gateway": {"name": "bench", "workers": 1}, "zenoh": {"listen": [free_endpoint()]},
        "buses": [{"name": f"can{i}", "transport": "can", "interface": interface, "channel": ch,
                   "devices": [{"name": f"w{i}-{n}", "kind": "zlac706", "id": n,
                                "follow_period_ms": 50, **heartbeat} for n in range(1, 6)]}
                  for i, ch in enumerate(channels)],
    })


def _daemon_run(config, seconds: float,
                sim_ids: list[int]) -> tuple[float, float, tuple[list[float], list[float]]]:
    """The daemon on ``config`` in this process, a subscriber taking its states in a child
    for ``seconds``: the daemon's CPU (this process's but for the threads ``sim_ids``) in % of
    a core, the states a second the subscriber took, and each state's ``ts`` less the one
    before of its device (s)."""
    loop, stop, ready = asyncio.new_event_loop(), asyncio.Event(), threading.Event()
    daemon = threading.Thread(target=loop.run_until_complete,
                              args=(serve(config, ready=ready, stop=stop),))
    daemon.start()
    ready.wait(20)
    time.sleep(1.0)
    endpoint = config.zenoh.listen[0]
    subscriber = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint, str(seconds)],
                                  stdout=subprocess.PIPE, text=True)
    try:
        subscriber.stdout.readline()
        cpu, sim_cpu = time.process_time(), sum(map(thread_cpu_s, sim_ids))
        started = time.monotonic()
        received = int(subscriber.stdout.readline())
        elapsed = time.monotonic() - started
        daemon_cpu = (time.process_time() - cpu) - (sum(map(thread_cpu_s, sim_ids)) - sim_cpu)
        steps = json.loads(subscriber.stdout.readline())
        ages = json.loads(subscriber.stdout.readline())
        return 100 * daemon_cpu / elapsed, received / seconds, (steps, ages)
    finally:
        subscriber.wait(10)
        loop.call_soon_threadsafe(stop.set)
        daemon.join(10)


def main() -> int:
    arguments(__doc__)
    with tempfile.TemporaryDirectory() as scratch_dir:
        scratch = Path(scratch_dir)
        hop = bare_hop()
        print(f"bare zenoh put → subscriber hop: p50 {ms(hop, .5)} ms, p99 {ms(hop, .99)} ms "
              f"({len(hop)} samples)")
        wire = command_to_wire(scratch)
        print(f"client get → frame on the wire: p50 {ms(wire, .5)} ms, p99 {ms(wire, .99)} ms "
              f"({len(wire)} samples); gateway adds {ms(wire, .5) - ms(hop, .5):.3f} ms at p50")
        for name, values in estop_latency(scratch).items():
            print(f"e-stop put → e-stop frame on {name}: p50 {ms(values, .5)} ms, "
                  f"p99 {ms(values, .99)} ms ({len(values)} e-stops)")
        for where, measure in (("in the daemon's process", telemetry_cpu),
                               ("in processes of their own", telemetry_cpu_apart)):
            cpu, rate = measure()
            print(f"20 devices {where}, heartbeats every 10 ms: {rate:.0f} state messages/s "
                  f"published, daemon CPU {cpu:.1f} % of one core")
        print(f"a device's states apart in time (ts, ms): {heartbeat_steps_apart()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
