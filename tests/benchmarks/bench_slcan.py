"""SLCAN adapters read through python-can's own ``slcan`` reads and through busgate's
(``gateway/bus/slcan.py``: a chunk a read, not a byte), turn about in one run; then a whole
gateway on four adapters.

Not a test (pytest does not collect it). The devices are ``busgate sim zlac706_can`` processes,
each five ZLAC706 heartbeating every 10 ms (1,000 frames a second) behind its simulated SLCAN
adapter on a pty.

1. One adapter, read by this process for ``SECONDS`` with each class in turn, ``ROUNDS`` times,
   in batches as a CAN owner reads while idle (every 8 ms, all that came): the frames a second
   taken and the reading thread's CPU.
2. Four adapters and ``busgate run`` on them (20 ZLAC706 at 100 Hz: bench_zenoh's telemetry
   part, with the devices in processes of their own): the daemon's CPU (its whole process,
   read from /proc) and the states a second a subscriber got of the 2,000 sent.

    .venv/bin/python tests/benchmarks/bench_slcan.py [SECONDS] [ROUNDS]
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_zenoh import SUBSCRIBER, free_endpoint
from can.interfaces.slcan import slcanBus
from usage import arguments

from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.slcan import SlcanBus

BUSGATE = str(Path(sys.executable).with_name("busgate"))
HEARTBEATING = ["--ids", "1,2,3,4,5", "--heartbeat-ms", "10"]
#: Frames are taken in batches this far apart, as a CAN owner takes them while idle.
BATCH_S = CanBusOwner.idle_batch_s


def simulator() -> tuple[subprocess.Popen, str]:
    """A simulator of five heartbeating ZLAC706 and its adapter's tty."""
    sim = subprocess.Popen([BUSGATE, "sim", "zlac706_can", *HEARTBEATING],
                           stdout=subprocess.PIPE, text=True)
    line = sim.stdout.readline()
    assert line.startswith("PORT "), line
    return sim, line.split()[1]


def read_for(kind: type[slcanBus], port: str, seconds: float) -> tuple[float, float]:
    """Frames a second read through ``kind`` and the reading thread's CPU, in %."""
    bus = kind(channel=port, bitrate=500_000, sleep_after_open=0)
    try:
        while bus.recv(timeout=0.5) is None:  # the adapter open, its frames coming
            pass
        frames, cpu, started = 0, time.thread_time(), time.monotonic()
        while (elapsed := time.monotonic() - started) < seconds:
            time.sleep(BATCH_S)
            while bus.recv(timeout=0) is not None:
                frames += 1
        return frames / elapsed, 100 * (time.thread_time() - cpu) / elapsed
    finally:
        bus.shutdown()


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def gateway_on_four(seconds: float, scratch: Path) -> tuple[float, float]:
    """The daemon's CPU in % and the states a second published, 20 ZLAC706 on four adapters."""
    sims = [simulator() for _ in range(4)]
    endpoint = free_endpoint()
    # one process: the daemon's CPU is its own
    config = [f'[gateway]\nname = "bench"\nworkers = 1\n[zenoh]\nlisten = ["{endpoint}"]\n']
    for bus, (_, port) in enumerate(sims):
        config.append(f'[[buses]]\nname = "can{bus}"\ntransport = "can"\ninterface = "slcan"\n'
                      f'channel = "{port}"\n')
        config += [f'[[buses.devices]]\nname = "w{bus}-{n}"\nkind = "zlac706"\nid = {n}\n'
                   "heartbeat_ms = 10\n" for n in range(1, 6)]
    (scratch / "gateway.toml").write_text("".join(config))
    daemon = subprocess.Popen([BUSGATE, "run", "--config", str(scratch / "gateway.toml")],
                              stderr=subprocess.DEVNULL)
    try:
        time.sleep(8.0)  # the buses up and every device online
        subscriber = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint, str(seconds)],
                                      stdout=subprocess.PIPE, text=True)
        subscriber.stdout.readline()
        cpu, started = cpu_s(daemon.pid), time.monotonic()
        received = int(subscriber.stdout.readline())
        used = (cpu_s(daemon.pid) - cpu) / (time.monotonic() - started)
        subscriber.wait(10)
        return 100 * used, received / seconds
    finally:
        for process in [daemon] + [sim for sim, _ in sims]:
            process.send_signal(signal.SIGINT)
        for process in [daemon] + [sim for sim, _ in sims]:
            process.wait(10)


def stopped(signum: int, frame: object) -> None:
    """SIGTERM (``timeout``, a test's kill) ends the run as Ctrl-C does: each ``finally``
    stops the simulators and the daemon it started, which would otherwise run on."""
    raise SystemExit(f"stopped by signal {signum}")


def main() -> int:
    signal.signal(signal.SIGTERM, stopped)
    given = arguments(
        __doc__,
        ("seconds", float, 5.0, "how long each reading measures"),
        ("rounds", int, 3, "how many rounds, turn about"),
    )
    seconds, rounds = given.seconds, given.rounds
    sim, port = simulator()
    try:
        for _ in range(rounds):
            for name, kind in (("python-can's reads", slcanBus), ("busgate's reads", SlcanBus)):
                rate, cpu = read_for(kind, port, seconds)
                print(f"one adapter, {name}: {rate:.0f} frames/s, reading thread {cpu:.1f} % "
                      f"({10_000 * cpu / rate:.1f} µs a frame)", flush=True)
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(10)
    with tempfile.TemporaryDirectory() as scratch:
        cpu, rate = gateway_on_four(seconds * 2, Path(scratch))
    print(f"busgate run, 20 ZLAC706 on four adapters: daemon CPU {cpu:.1f} % of one core, "
          f"{rate:.0f} states/s published")
    return 0


if __name__ == "__main__":
    sys.exit(main())
