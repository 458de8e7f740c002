"""The zenoh API's figures: command latency to the wire, e-stop latency, telemetry CPU.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off: the simulators and the daemon (``busgate run``) as child processes,
the client here. Clocks are comparable across processes (perf_counter is CLOCK_MONOTONIC).

    .venv/bin/python tests/benchmarks/bench_zenoh.py

1. A client's get on a device's cmd key → its frame on the wire (the simulator's arrival
   time), p50/p99, beside a bare zenoh put → subscriber hop between two sessions measured in
   the same run. The gateway should add under 1 ms at p50.
2. An e-stop put → the e-stop frame on every bus, while every bus streams and polls (3 LA
   actuators at 921600 baud, 2 DS servos at 1 Mbaud, each polled at 50 Hz): p99.
3. 20 devices with 100 Hz telemetry (ZLAC706 heartbeats every 10 ms, four SLCAN buses of
   five): the daemon's CPU, from /proc.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from busgate.codecs import inspire_la as la
from busgate.gateway.bus.stats import percentile
from busgate.gateway.clock import now
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import load_records
from busgate.gateway.zenoh_config import session_config


def free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def ms(values: list[float], q: float) -> float:
    return round(percentile(sorted(values), q) * 1000, 3)


class Daemon:
    """``busgate run`` on a config written from ``buses`` (TOML text)."""

    def __init__(self, scratch: Path, endpoint: str, buses: str) -> None:
        config = scratch / "gw.toml"
        config.write_text(f'[gateway]\nname = "bench"\n[zenoh]\nlisten = ["{endpoint}"]\n{buses}')
        self.process = subprocess.Popen(
            [sys.executable, "-m", "busgate.gateway.cli", "run", "--config", str(config),
             "--log-level", "warning"])

    def cpu_s(self) -> float:
        fields = Path(f"/proc/{self.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        self.process.wait(10)


def serial_bus(name: str, port: str, kind: str, ids: list[int], baud: int, **extra) -> str:
    text = f'[[buses]]\nname = "{name}"\ntransport = "serial"\nport = "{port}"\nbaudrate = {baud}\n'
    for i in ids:
        text += f'[[buses.devices]]\nname = "{name}-{i}"\nkind = "{kind}"\nid = {i}\n'
        text += "".join(f"{k} = {v}\n" for k, v in extra.items())
    return text


def wait_ready(client: zenoh.Session, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reply in client.get("busgate/bench/info", timeout=1):
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
                if i % 2000 == 1999:
                    sent.clear()
        finally:
            client.close()
            daemon.stop()
    arrivals = {r.wire: r.arrived for r in load_records(record) if r.frame == "MoveCommand"}
    return [arrivals[w] - t for w, t in sent.items() if w in arrivals]


def estop_latency(scratch: Path, rounds: int = 100) -> dict[str, list[float]]:
    records = [scratch / "e1.jsonl", scratch / "e2.jsonl"]
    with (SimProcess("inspire_la", ["--ids", "1,2,3", "--record", str(records[0])]) as s1,
          SimProcess("ds_servo", ["--ids", "1,2", "--record", str(records[1]),
                                  "--baudrate", "1000000"]) as s2):
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


def telemetry_cpu(scratch: Path, seconds: float = 10.0) -> tuple[float, float]:
    sims = [SimProcess("zlac706_can", ["--ids", "1,2,3,4,5", "--heartbeat-ms", "10"])
            for _ in range(4)]
    endpoint = free_endpoint()
    buses = ""
    for index, sim in enumerate(sims):
        buses += (f'[[buses]]\nname = "can{index}"\ntransport = "can"\ninterface = "slcan"\n'
                  f'channel = "{sim.port}"\noptions = {{ sleep_after_open = 0 }}\n')
        for node in range(1, 6):
            buses += (f'[[buses.devices]]\nname = "w{index}-{node}"\nkind = "zlac706"\n'
                      f"id = {node}\nheartbeat_ms = 10\n")
    daemon = Daemon(scratch, endpoint, buses)
    client = zenoh.open(session_config(connect=[endpoint]))
    received = [0]
    subscriber = client.declare_subscriber("busgate/bench/dev/*/state",
                                           lambda s: received.__setitem__(0, received[0] + 1))
    try:
        wait_ready(client)
        cpu, count, started = daemon.cpu_s(), received[0], time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - started
        return (100 * (daemon.cpu_s() - cpu) / elapsed, (received[0] - count) / elapsed)
    finally:
        subscriber.undeclare()
        client.close()
        daemon.stop()
        for sim in sims:
            sim.stop()


def main() -> int:
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
        cpu, rate = telemetry_cpu(scratch)
        print(f"20 devices, heartbeats every 10 ms: {rate:.0f} state messages/s published, "
              f"daemon CPU {cpu:.1f} % of one core")
    return 0


if __name__ == "__main__":
    sys.exit(main())
