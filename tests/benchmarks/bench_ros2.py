"""The ROS 2 face's cost: the daemon's CPU with joint states at 100 Hz, with and without the
face, and a command's latency from a put to the wire, a ROS JointState against the gateway's
own JSON follow target, measured in the same run.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: the Inspire LA simulator and the daemon (``busgate run``) as child
processes, the publishers here. Clocks are comparable across processes (CLOCK_MONOTONIC).

    .venv/bin/python tests/benchmarks/bench_ros2.py [--pairs 3] [--seconds 10] [--samples 100]

1. CPU: two LA actuators polled at 100 Hz (so the joints message, and with the face the
   JointState, goes out at 100 Hz), a subscriber of each counting what arrives; the daemon's
   CPU over ``--seconds``, runs with and without ``[ros2]`` taken in turn (``--pairs``).
2. Latency: a put of a JointState on ``robot_joint_commands`` (CDR, rmw_zenoh's attachment)
   and, once the face's claim lapsed, a put of ``{"position": x}`` on the device's follow key,
   each to a new target on an idle line; the time from the put to the target's follow frame
   arriving at the simulator. Both start a stream that ticks at once; the ROS one passes the
   face first.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from busgate.codecs import inspire_la as la
from busgate.codecs.ros2 import messages, rmw_zenoh
from busgate.gateway.bus.clock import now
from busgate.gateway.ros2.face import CLAIM_TTL_S
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import load_records
from busgate.schemas.zenoh_session import session_config

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_zenoh import Daemon, free_endpoint, ms, serial_bus, wait_ready

JOINT_STATE = "sensor_msgs/msg/JointState"
COMMANDS = "/robot_joint_commands"
STATES = "/robot_joint_states"


def buses(port: str, poll_hz: int, ros2: bool) -> str:
    text = serial_bus("uart0", port, "inspire_la", [1, 2], 921600, poll_hz=poll_hz)
    return text + ("[ros2]\n" if ros2 else "")


def cpu_run(scratch: Path, port: str, ros2: bool, seconds: float) -> tuple[float, float]:
    """The daemon's CPU share over ``seconds`` and the messages a second its subscriber got."""
    endpoint = free_endpoint()
    daemon = Daemon(scratch, endpoint, buses(port, 100, ros2))
    client = zenoh.open(session_config(connect=[endpoint]))
    count = [0]
    key = (rmw_zenoh.data_key(0, STATES, JOINT_STATE, "jazzy") if ros2
           else "busgate/bench/joints")
    subscriber = client.declare_subscriber(key, lambda sample: count.__setitem__(0, count[0] + 1))
    try:
        wait_ready(client)
        time.sleep(1.0)
        cpu, wall, got = daemon.cpu_s(), time.monotonic(), count[0]
        time.sleep(seconds)
        cpu, wall, got = daemon.cpu_s() - cpu, time.monotonic() - wall, count[0] - got
    finally:
        subscriber.undeclare()
        client.close()
        daemon.stop()
    return cpu / wall, got / wall


def latency_run(scratch: Path, samples: int) -> dict[str, list[float]]:
    record = scratch / "latency.jsonl"
    sent: dict[str, dict[int, float]] = {"ros2": {}, "json": {}}
    with SimProcess("inspire_la", ["--ids", "1", "--record", str(record),
                                   "--busy-poll-ms", "0"]) as sim:
        endpoint = free_endpoint()
        config = serial_bus("uart0", sim.port, "inspire_la", [1], 921600, poll_hz=1)
        daemon = Daemon(scratch, endpoint, config + "[ros2]\n")
        client = zenoh.open(session_config(connect=[endpoint]))
        commands = client.declare_publisher(rmw_zenoh.data_key(0, COMMANDS, JOINT_STATE, "jazzy"))
        gid = rmw_zenoh.new_gid()
        try:
            wait_ready(client)
            time.sleep(0.5)
            # The JSON targets after the ROS ones: the face holds the joint for its client
            # while its commands come, and 2 s after (``face.CLAIM_TTL_S``).
            for way in ("ros2", "json"):
                for i in range(samples):
                    target = 100 + 2 * i + (way == "json")
                    sent[way][target] = now()
                    if way == "ros2":
                        payload = messages.encode(JOINT_STATE, {"name": ["uart0-1"],
                                                                "position": [float(target)]})
                        attachment = rmw_zenoh.attachment(i + 1, time.time_ns(), gid)
                        commands.put(payload, attachment=attachment)
                    else:
                        client.put("busgate/bench/dev/uart0-1/follow",
                                   json.dumps({"position": target}))
                    time.sleep(0.15)  # the JSON stream goes stale first: each starts anew
                time.sleep(CLAIM_TTL_S + 0.5)
        finally:
            client.close()
            daemon.stop()
    arrived: dict[int, float] = {}
    for r in load_records(record):
        if r.direction == "rx" and r.frame in ("FollowCommand", "GroupFollowCommand"):
            decoder = la.CommandDecoder()
            decoder.feed(bytes.fromhex(r.wire))
            for frame in decoder.events():
                for target in getattr(frame, "targets", None) or [frame]:
                    arrived.setdefault(target.position_raw, r.arrived or r.start)
    return {way: [arrived[t] - s for t, s in times.items() if t in arrived]
            for way, times in sent.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--samples", type=int, default=100)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        scratch = Path(folder)
        runs: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
        with SimProcess("inspire_la", ["--ids", "1,2", "--busy-poll-ms", "0"]) as sim:
            for _ in range(args.pairs):
                for ros2 in (False, True):
                    runs[ros2].append(cpu_run(scratch, sim.port, ros2, args.seconds))
        for ros2, label in ((False, "without [ros2]"), (True, "with [ros2]")):
            shares = [share for share, _ in runs[ros2]]
            rates = [rate for _, rate in runs[ros2]]
            print(f"CPU {label}: median {statistics.median(shares) * 100:.1f} % "
                  f"(runs {', '.join(f'{s * 100:.1f}' for s in shares)}); "
                  f"messages/s {statistics.median(rates):.1f}")
        latencies = latency_run(scratch, args.samples)
        for way, values in latencies.items():
            print(f"put → wire, {way}: p50 {ms(values, 0.5)} ms, p99 {ms(values, 0.99)} ms "
                  f"({len(values)} of {args.samples})")


if __name__ == "__main__":
    main()
