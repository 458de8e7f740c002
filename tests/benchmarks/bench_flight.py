"""What the daemon's flight recorder costs, and whether writing an incident disturbs a stream.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: the simulators and the daemon (``busgate run``) as child processes,
the streaming client here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_flight.py [--ring-seconds 60] [--measure 20]

The gateway: 20 devices at full rate. 5 Inspire LA at 921600 baud, polled at 40 Hz and all
streamed at a 10 ms follow period (the client here sends each a target every 10 ms); 15
ZLAC706 on three SLCAN buses of five, each sending heartbeats every 10 ms (100 Hz telemetry).

1. Cost: the daemon run twice on the same load, without ``[recorder]`` and with it; its CPU
   (utime + stime from /proc, % of one core) over ``--measure`` seconds, and its RSS once the
   ring is full (``--ring-seconds`` and 5 s more): the difference is what the recorder takes.
   The incident file's size per ring second, per device.
2. Follow jitter while an incident is written: SIGUSR1 three times, each after the hold-off;
   the third file's frames (60 s of the LA bus as the gateway wrote them, its own timestamps)
   hold the follow ticks during the first two writes. Each follow interval minus the period,
   p50/p99/max, inside the write windows (from the trigger plus ``AFTER_S`` to the file's
   mtime) against every other interval of the same file: the baseline of the same run.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path

import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready
from mcap.reader import make_reader

from busgate.codecs import inspire_la as la
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import follow_frame_names
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.recording.flight import AFTER_S, HOLDOFF_S
from busgate.gateway.sim.process import SimProcess
from busgate.schemas.zenoh_session import session_config

LA_IDS = (1, 2, 3, 4, 5)
CAN_BUSES = ("can0", "can1", "can2")
CAN_IDS = (1, 2, 3, 4, 5)
DEVICES = len(LA_IDS) + len(CAN_BUSES) * len(CAN_IDS)
FOLLOW_PERIOD_MS = 10
HEARTBEAT_MS = 10
#: Not streamed here, but the bus budget reserves their follow ticks: the longest period.
CAN_FOLLOW_PERIOD_MS = 50
LA_POLL_HZ = 40
WARM_UP_S = 5.0
INCIDENTS = 3


def can_bus(name: str, port: str) -> str:
    text = (
        f'[[buses]]\nname = "{name}"\ntransport = "can"\ninterface = "slcan"\n'
        f'channel = "{port}"\noptions = {{ sleep_after_open = 0 }}\n'
    )
    for ident in CAN_IDS:
        text += (
            f'[[buses.devices]]\nname = "{name}-{ident}"\nkind = "zlac706"\nid = {ident}\n'
            f"heartbeat_ms = {HEARTBEAT_MS}\nfollow_period_ms = {CAN_FOLLOW_PERIOD_MS}\n"
        )
    return text


def buses(ports: dict[str, str]) -> str:
    return serial_bus(
        "la",
        ports["la"],
        "inspire_la",
        list(LA_IDS),
        921_600,
        poll_hz=LA_POLL_HZ,
        follow_period_ms=FOLLOW_PERIOD_MS,
    ) + "".join(can_bus(name, ports[name]) for name in CAN_BUSES)


def stream(endpoint: str, stop: threading.Event) -> None:
    """Every LA a new target each follow period (a sine), until ``stop``."""
    config = session_config(connect=[endpoint])
    with zenoh.open(config) as session:
        for ident in LA_IDS:
            session.get(
                f"busgate/bench/dev/la-{ident}/cmd", payload='{"op":"enable"}', timeout=5
            ).recv()
        start = time.monotonic()
        while not stop.is_set():
            t = time.monotonic() - start
            target = json.dumps({"position": round(1000 + 500 * math.sin(2 * math.pi * t))})
            for ident in LA_IDS:
                session.put(f"busgate/bench/dev/la-{ident}/follow", target)
            time.sleep(FOLLOW_PERIOD_MS / 1000)


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


def run_daemon(scratch: Path, ports: dict[str, str], recorder: str, args, during=None) -> dict:
    """The daemon on the load: its CPU over ``--measure`` s, RSS once a ring would be full,
    and what ``during(daemon)`` returns."""
    endpoint = free_endpoint()
    daemon = Daemon(scratch, endpoint, recorder + buses(ports))
    stop = threading.Event()
    streamer = threading.Thread(target=stream, args=(endpoint, stop))
    try:
        with zenoh.open(session_config(connect=[endpoint])) as probe:
            wait_ready(probe)
        streamer.start()
        time.sleep(WARM_UP_S)
        cpu_before, started = daemon.cpu_s(), time.monotonic()
        time.sleep(args.measure)
        cpu = 100 * (daemon.cpu_s() - cpu_before) / (time.monotonic() - started)
        time.sleep(max(0.0, args.ring_seconds + 5 - args.measure - WARM_UP_S))
        figures = {"cpu_percent": cpu, "rss_mib": rss_mib(daemon.process.pid)}
        if during is not None:
            figures |= during(daemon)
        return figures
    finally:
        stop.set()
        if streamer.is_alive():
            streamer.join()
        daemon.stop()


def incidents(folder: Path) -> list[Path]:
    return sorted(folder.glob("incident-*.mcap"), key=lambda path: path.stat().st_mtime)


def write_incidents(folder: Path):
    """SIGUSR1 ``INCIDENTS`` times, each once the hold-off has passed: for each file, the
    wall time its writing started (trigger + ``AFTER_S``) and ended (its mtime), and the
    daemon's CPU while it wrote."""

    def during(daemon: Daemon) -> dict:
        windows = []
        for count in range(1, INCIDENTS + 1):
            triggered, cpu_before = time.time(), daemon.cpu_s()
            daemon.process.send_signal(signal.SIGUSR1)
            while len(incidents(folder)) < count:
                time.sleep(0.05)
            path = incidents(folder)[-1]
            ended = path.stat().st_mtime
            windows.append((triggered + AFTER_S, ended, daemon.cpu_s() - cpu_before, path))
            time.sleep(max(0.0, HOLDOFF_S + 1 - (time.time() - triggered)))
        return {"windows": windows}

    return during


def follow_errors_ms(path: Path) -> list[tuple[float, float]]:
    """(wall time, interval − period in ms) of every follow tick of the LA bus in ``path``."""
    follow = follow_frame_names([InspireLaDriver(f"la-{i}", i) for i in LA_IDS])
    ticks = []
    with path.open("rb") as stream:
        for _, _, message in make_reader(stream).iter_messages(
            topics=["busgate/bench/bus/la/frames"], log_time_order=True
        ):
            frame = json.loads(message.data)
            if frame["dir"] != "tx":
                continue
            decoder = la.CommandDecoder()
            decoder.feed(bytes.fromhex(frame["wire"]))
            if any(type(event).__name__ in follow for event in decoder.events()):
                ticks.append(frame["ts"])
    return [(b, (b - a) * 1000 - FOLLOW_PERIOD_MS) for a, b in itertools.pairwise(ticks)]


def spread(errors: list[float]) -> str:
    ordered = sorted(errors)
    return (
        f"p50 {percentile(ordered, 0.5):+.3f} ms, p99 {percentile(ordered, 0.99):+.3f} ms, "
        f"max {ordered[-1]:+.3f} ms over {len(ordered)} intervals"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ring-seconds", type=float, default=60.0)
    parser.add_argument("--measure", type=float, default=20.0)
    args = parser.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="bench-flight-"))
    folder = scratch / "incidents"
    with contextlib.ExitStack() as stack:
        ports = {
            "la": stack.enter_context(
                SimProcess("inspire_la", ["--ids", ",".join(map(str, LA_IDS))])
            ).port
        }
        for name in CAN_BUSES:
            ports[name] = stack.enter_context(
                SimProcess(
                    "zlac706_can",
                    ["--ids", ",".join(map(str, CAN_IDS)), "--heartbeat-ms", str(HEARTBEAT_MS)],
                )
            ).port
        off = run_daemon(scratch, ports, "", args)
        recorder = f'[recorder]\nseconds = {args.ring_seconds}\ndir = "{folder}"\n'
        on = run_daemon(scratch, ports, recorder, args, during=write_incidents(folder))
    windows = on["windows"]
    sizes = [path.stat().st_size for *_, path in windows]
    per_device = sizes[-1] / args.ring_seconds / DEVICES / 1024
    print(
        f"1. {DEVICES} devices at full rate (5 LA polled at {LA_POLL_HZ} Hz and streamed at "
        f"10 ms, 15 ZLAC706 on CAN with 100 Hz heartbeats), the daemon's CPU: "
        f"{off['cpu_percent']:.1f} % of a core without the recorder, "
        f"{on['cpu_percent']:.1f} % with it; RSS "
        f"{off['rss_mib']:.0f} MiB without, {on['rss_mib']:.0f} MiB with a full "
        f"{args.ring_seconds:g} s ring (+{on['rss_mib'] - off['rss_mib']:.0f} MiB); an incident"
        f" file {sizes[-1] / 1024 / 1024:.1f} MiB ({per_device:.1f} KiB per device per second"
        f" kept)"
    )
    for start, end, cpu, path in windows:
        print(
            f"   incident {path.name}: written in {end - start:.2f} s (the daemon meanwhile "
            f"{cpu:.2f} s of CPU)"
        )
    errors = follow_errors_ms(windows[-1][3])
    writing = [
        error for t, error in errors if any(start <= t <= end for start, end, *_ in windows[:-1])
    ]
    other = [
        error
        for t, error in errors
        if not any(start <= t <= end for start, end, *_ in windows[:-1])
    ]
    print(
        f"2. LA follow interval − period, gateway side, from the last incident file:\n"
        f"   while incidents were written: {spread(writing)}\n"
        f"   the rest of the same {args.ring_seconds:g} s: {spread(other)}"
    )
    shutil.rmtree(scratch)


if __name__ == "__main__":
    main()
