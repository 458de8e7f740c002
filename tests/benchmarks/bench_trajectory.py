"""A trajectory played by the gateway: how well the buses keep its grid, and what they send.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off: the simulators (``busgate sim``, recording every frame) and the daemon
(``busgate run``) as child processes, the client here. Clocks are comparable across processes
(perf_counter is CLOCK_MONOTONIC), and a wall time converts to it by the offset of the two
clocks read together here, as the daemon converts ``start_at``.

    .venv/bin/python tests/benchmarks/bench_trajectory.py [--plays 2] [--seconds 3]
                                                         [--busy-poll-ms 0]

3 Inspire LA actuators on one bus (921600 baud), 2 DS servos on another (1 Mbaud), each
device at its default 20 ms follow period and 10 Hz polls; ``--plays`` cubic trajectories
of ``--seconds`` each through ``<prefix>/<gw>/trajectory``, each ``start_at`` 0.3 s ahead,
every device moving on every point. From the simulators' records (when each frame was read
off its pty: late by the simulator's own wake-up, tens of µs sleeping in select, a few µs
with ``--busy-poll-ms``), each tick frame's slot is the last one before it arrived (a tick
goes out at its slot or after it):

1. Alignment: per slot both buses ticked, |t_LA − t_DS|, p50/p99/max in µs.
2. Each bus's first tick against ``start_at``, in µs (every play), and the slots with no
   tick (the grid is the period stretched by ``GRID_STRETCH``; a tick more than ``ON_TIME_S``
   late moves the next to the first slot a period on).
3. Sampling error, in units: each value sent against the analytic trajectory (the pure
   interpolant, unrounded) at its slot's time (rounding alone: 0.5 at most) and at the time
   the frame arrived (what the jitter would cost were the path sampled then), p50/p99/max.
4. The daemon's own follow figures (``<prefix>/<gw>/bus/<bus>/stats``): intervals against the
   period (the least, p99) and the smallest UART gap.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import percentile
from busgate.gateway.scheduler.trajectory_ticks import GRID_STRETCH
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.recorder import WireRecord
from busgate.gateway.sim.wire_analysis import load_records
from busgate.gateway.trajectory.interpolation import Path as Trajectory
from busgate.gateway.trajectory.interpolation import paths_of
from busgate.schemas.trajectory import TrajectoryPlay
from busgate.schemas.zenoh_session import session_config

PERIOD_S = 0.02  # every device's default follow period
GRID_S = PERIOD_S * GRID_STRETCH  # the slots' spacing (rule 1 of trajectory_ticks.py)
LEAD_S = 0.3
LA = ["la-1", "la-2", "la-3"]
DS = ["ds-1", "ds-2"]
DEVICES = [*LA, *DS]
#: Each bus's tick frame and its codec.
TICKS = {"la": (la, la.GroupFollowCommand), "ds": (ds, ds.SyncWrite)}


def points(seconds: float, play: int) -> list[dict]:
    """A cubic through a point every half second, each device swinging between two values
    with a speed at each point (the LA range is 0–2000, the DS range 0–4095)."""
    count = max(1, round(seconds / 0.5))
    result = []
    for i in range(1, count + 1):
        up = (i + play) % 2 == 0
        result.append({
            "t_s": round(i * seconds / count, 6),
            "positions": [1700 if up else 300, 300 if up else 1700, 1000 + (300 if up else -300),
                          3500 if up else 600, 600 if up else 3500],
            "velocities": [0.0 if i == count else v for v in (400, -400, 200, 800, -800)],
        })
    return result


def start_values(client: zenoh.Session) -> list[float]:
    """Each device's target as its state has it (where the daemon starts its path), once
    every device has been read since this call (after a play, a target read before its last
    tick would be stale: the daemon starts from that tick's value then)."""
    mark = time.time()
    while True:
        [reply] = [r for r in client.get("busgate/bench/info", timeout=5) if r.ok]
        info = json.loads(reply.ok.payload.to_bytes())
        states = {d["name"]: d["state"] for b in info["buses"] for d in b["devices"]}
        if all(states[d]["ts"] > mark for d in DEVICES):
            return [float(states[d]["target"] if states[d]["target"] is not None
                          else states[d]["position"]) for d in DEVICES]
        time.sleep(0.05)


def play(client: zenoh.Session, seconds: float, index: int) -> tuple[float, dict[str, Trajectory]]:
    """One play, to its result: its start (bus clock) and each device's path."""
    results: list[dict] = []
    key = f"busgate/bench/trajectory/bench{index}/feedback"
    subscriber = client.declare_subscriber(
        key, lambda s: results.append(json.loads(s.payload.to_bytes())))
    try:
        starts = start_values(client)
        start_at = time.time() + LEAD_S
        command = {"op": "play", "id": f"bench{index}", "devices": DEVICES,
                   "interpolation": "cubic", "start_at": start_at,
                   "points": points(seconds, index)}
        start_bus = now() + (start_at - time.time())
        [reply] = [json.loads(r.ok.payload.to_bytes())
                   for r in client.get("busgate/bench/trajectory", payload=json.dumps(command),
                                       timeout=5) if r.ok]
        if not reply["ok"]:
            raise RuntimeError(f"play refused: {reply}")
        deadline = time.monotonic() + LEAD_S + seconds + 5
        while not any("result" in r for r in results):
            if time.monotonic() > deadline:
                raise RuntimeError("no result")
            time.sleep(0.05)
        result = next(r for r in results if "result" in r)
        if result["result"] != "succeeded":
            raise RuntimeError(f"the play ended {result}")
    finally:
        subscriber.undeclare()
    paths = paths_of(TrajectoryPlay.model_validate(command), starts)
    return start_bus, dict(zip(DEVICES, paths, strict=True))


def tick_times(records: list[WireRecord], bus: str, start_bus: float,
               end_bus: float) -> dict[int, tuple[float, list[int]]]:
    """Slot → (arrival, the values of the bus's devices in id order) of each tick frame."""
    codec, frame_type = TICKS[bus]
    found: dict[int, tuple[float, list[int]]] = {}
    for record in records:
        arrived = record.arrived or record.start
        if record.direction != "rx" or not start_bus - 0.001 <= arrived <= end_bus:
            continue
        decoder = codec.CommandDecoder()
        decoder.feed(bytes.fromhex(record.wire))
        for frame in decoder.events():
            if isinstance(frame, frame_type):
                slot = math.floor((arrived - start_bus) / GRID_S + 0.01)  # at or after it
                values = [t.position_raw for t in sorted(frame.targets, key=lambda t: t.device_id)]
                found[slot] = (arrived, values)
    return found


def stats_of(client: zenoh.Session) -> tuple[dict[str, dict], zenoh.Subscriber]:
    latest: dict[str, dict] = {}
    lock = threading.Lock()

    def received(sample: zenoh.Sample) -> None:
        body = json.loads(sample.payload.to_bytes())
        with lock:
            latest[body["bus"]] = body

    return latest, client.declare_subscriber("busgate/bench/bus/*/stats", received)


def spread(values: list[float], scale: float, digits: int = 1) -> str:
    ordered = sorted(values)
    return (f"p50 {round(percentile(ordered, 0.5) * scale, digits)}, "
            f"p99 {round(percentile(ordered, 0.99) * scale, digits)}, "
            f"max {round(ordered[-1] * scale, digits)} ({len(values)})")


def main() -> int:
    arguments = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    arguments.add_argument("--plays", type=int, default=2)
    arguments.add_argument("--seconds", type=float, default=3.0)
    arguments.add_argument("--busy-poll-ms", type=float, default=0.0)
    options = arguments.parse_args()
    quiet = ["--busy-poll-ms", str(options.busy_poll_ms)]
    with tempfile.TemporaryDirectory() as scratch_dir:
        scratch = Path(scratch_dir)
        records = {"la": scratch / "la.jsonl", "ds": scratch / "ds.jsonl"}
        with (SimProcess("inspire_la", ["--ids", "1,2,3", "--record", str(records["la"]),
                                        *quiet]) as la_sim,
              SimProcess("ds_servo", ["--ids", "1,2", "--baudrate", "1000000",
                                      "--record", str(records["ds"]), *quiet]) as ds_sim):
            endpoint = free_endpoint()
            buses = (serial_bus("la", la_sim.port, "inspire_la", [1, 2, 3], 921600)
                     + serial_bus("ds", ds_sim.port, "ds_servo", [1, 2], 1_000_000))
            daemon = Daemon(scratch, endpoint, buses)
            client = zenoh.open(session_config(connect=[endpoint]))
            try:
                wait_ready(client)
                stats, subscriber = stats_of(client)
                plays = [play(client, options.seconds, i) for i in range(options.plays)]
                time.sleep(1.2)  # the statistics of the last play's second
                subscriber.undeclare()
            finally:
                client.close()
                daemon.stop()
        loaded = {bus: load_records(path) for bus, path in records.items()}
    report(plays, loaded, stats, options.seconds)
    return 0


def report(plays, loaded, stats, seconds: float) -> None:
    aligned, firsts, at_slot, at_arrival = [], {"la": [], "ds": []}, [], []
    missed = {"la": 0, "ds": 0}
    late: dict[str, list[float]] = {"la": [], "ds": []}
    slots_total = 0
    for index, (start_bus, paths) in enumerate(plays):
        # Its ticks: to its result (a few held ticks after its end), before the next's start.
        following = plays[index + 1][0] if index + 1 < len(plays) else float("inf")
        end_bus = min(start_bus + seconds + 0.5, following - 0.001)
        ticks = {bus: tick_times(loaded[bus], bus, start_bus, end_bus) for bus in TICKS}
        last = math.floor(seconds / GRID_S + 1e-9)
        slots_total += last + 1
        for bus, found in ticks.items():
            firsts[bus].append(found[0][0] - start_bus)
            missed[bus] += sum(1 for k in range(last + 1) if k not in found)
            names = LA if bus == "la" else DS
            for k, (arrived, values) in found.items():
                late[bus].append(arrived - (start_bus + k * GRID_S))
                for name, value in zip(names, values, strict=True):
                    at_slot.append(abs(value - paths[name].at(k * GRID_S)))
                    at_arrival.append(abs(value - paths[name].at(arrived - start_bus)))
        for k in ticks["la"].keys() & ticks["ds"].keys():
            aligned.append(abs(ticks["la"][k][0] - ticks["ds"][k][0]))
    print(f"{len(plays)} cubic plays of {seconds:g} s, {slots_total} slots per bus "
          f"(period {PERIOD_S * 1000:g} ms, grid {GRID_S * 1000:g} ms); 3 LA at 921600 baud, "
          "2 DS at 1 Mbaud")
    print(f"alignment |t_LA − t_DS| per slot, µs: {spread(aligned, 1e6)}")
    for bus, values in firsts.items():
        shown = ", ".join(f"{v * 1e6:.0f}" for v in values)
        print(f"first tick on {bus} after start_at, µs: {shown}; slots without a tick: "
              f"{missed[bus]}; each tick after its slot, µs: {spread(late[bus], 1e6)}")
    print(f"sampling error at the slot's time, units: {spread(at_slot, 1, 3)}")
    print(f"sampling error at the arrival time, units: {spread(at_arrival, 1, 3)}")
    for bus, body in sorted(stats.items()):
        least, p99 = body["follow_error_min_s"], body["follow_error_p99_s"]
        under = "none" if least >= 0 else "some"
        print(f"daemon, bus {bus}: follow interval − period least {least * 1e6:.0f} µs "
              f"({under} under the period), p99 {p99 * 1e6:.0f} µs "
              f"({body['follow_intervals']} intervals); smallest gap "
              f"{body['smallest_gap_s'] * 1e6:.0f} µs")


if __name__ == "__main__":
    sys.exit(main())
