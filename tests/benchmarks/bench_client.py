"""What the SDK (``busgate.client``) costs over bare zenoh: command latency, follow puts, connect.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off: ``busgate demo --listen tcp/127.0.0.1:<free port>`` as a child
process (started and ended by its PID), every client session here.

    .venv/bin/python tests/benchmarks/bench_client.py [--count 500] [--seconds 2] [--op status]
                                                     [--profile]

1. Command latency: the same command on ``demo/la1``, ``--count`` times each, (a) as a bare
   zenoh get (a client-mode session, the command's JSON encoded once, the replies collected),
   (b) as ``Device.send`` of the sync face, (c) as ``await Device.send`` of the asyncio face,
   interleaved (the order turns each round: a, b, c / b, c, a / c, a, b) so that machine noise
   and the bus's own rhythm hit all three alike. p50 and p99 of each, and of the per-round
   differences (SDK − bare), in µs. The default command is ``{"op": "status"}``: a read, so it
   needs no claim, moves nothing and does the same exchange every time; it answers in about
   3 ms, most of it the gateway's bus schedule (the status frame at 921600 baud). ``--op
   release`` (a release of a claim nobody holds) is answered by the gateway without the bus, in
   well under a millisecond, and shows the SDK's share with less of the bus's jitter around
   it; ``--op move`` moves la1 between 100 and 200 (a motion command).
2. Follow puts: inside ``with la1.claim(), la1.follow() as f``, ``f.set(position=1000)`` in a
   tight loop, against a bare ``session.put`` of the same JSON on the follow key and a bare
   express publisher's put (how ``set`` sends), ``--seconds`` each, interleaved in slices of
   0.25 s: calls per second and this process's CPU (``time.process_time``, zenoh's threads
   included) per call, and the puts ``Follow.set`` sent (it spaces them 10 ms apart at least,
   the latest target winning). The bare loops put more than the gateway digests: zenoh then
   drops puts at the sender (congestion control "drop"), and a dropped put returns sooner than
   a sent one, so theirs are the rates the calls return at, not the rates delivered; how long
   the gateway then takes to answer again is printed with them. A second block checks that a
   claim of the default TTL (2 s) holds under a tight loop of sets (before the SDK spaced its
   puts, its renewals queued behind thousands of puts and it was lost after 3.3 s).
3. ``bc.connect`` → the first ``device()`` resolved (its ``info`` query), five times, sync and
   asyncio.

``--profile`` adds cProfile's top functions (by own time) of ``Device.send`` and
``Follow.set`` on this thread; zenoh's callbacks (reply parsing, settling the futures) run on
other threads, which cProfile does not see.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import functools
import json
import pstats
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

import busgate.client as bc
from busgate.gateway.bus.stats import percentile
from busgate.schemas.zenoh_session import session_config

DEVICE = "demo/la1"
CMD_KEY = "busgate/demo/dev/la1/cmd"
FOLLOW_KEY = "busgate/demo/dev/la1/follow"
TIMEOUT_S = 5.0
WARMUP = 20
SLICE_S = 0.25
CONNECTS = 5
CLAIM_WATCH_S = 6.0
DRAIN_S = 30.0
FOLLOW_TARGET = {"position": 1000}


def free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def us(values: list[float], q: float) -> float:
    return round(percentile(sorted(values), q) * 1e6)


class Demo:
    """``busgate demo`` as a child process, until ``stop`` (SIGTERM to its PID)."""

    def __init__(self, scratch: Path, endpoint: str) -> None:
        self.log = scratch / "demo.log"
        with self.log.open("w") as log:  # the demo logs to stderr: a file, never a full pipe
            self.process = subprocess.Popen(
                [sys.executable, "-m", "busgate.gateway.cli", "demo", "--listen", endpoint],
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
            )
        assert self.process.stdout is not None
        for line in self.process.stdout:  # the hints are printed once the gateway serves
            if "is serving on" in line:
                return
        self.stop()
        raise RuntimeError(f"busgate demo did not serve:\n{self.log.read_text()[-2000:]}")

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5)


def commands(op: str) -> Callable[[int], dict[str, Any]]:
    """The ``i``-th command sent (a move alternates between two positions)."""
    if op == "move":
        return lambda i: {"op": "move", "position": 100 + 100 * (i % 2)}
    return lambda i: {"op": op}


def bare_get(session: zenoh.Session, payload: bytes) -> list[bytes]:
    """A get as a program without the SDK sends it: zenoh's default handler (a channel this
    thread reads), the replies' payloads collected."""
    handler = session.get(CMD_KEY, payload=payload, timeout=TIMEOUT_S)
    replies = [reply.ok.payload.to_bytes() for reply in handler if reply.ok]
    if not replies:
        raise RuntimeError(f"no ok reply on {CMD_KEY}")
    return replies


async def latency(endpoint: str, op: str, count: int) -> dict[str, list[float]]:
    """Seconds per command of each way, ``count`` rounds (after ``WARMUP``), interleaved."""
    command = commands(op)
    bare = zenoh.open(session_config(mode="client", connect=[endpoint]))
    client = bc.connect(endpoint, client_id="bench-sync", timeout=TIMEOUT_S)
    times: dict[str, list[float]] = {"bare": [], "sync": [], "aio": []}
    try:
        device = client.device(DEVICE)
        async with bc.aio.connect(endpoint, client_id="bench-aio", timeout=TIMEOUT_S) as aclient:
            adevice = await aclient.device(DEVICE)
            sent = 0

            async def one(way: str) -> float:
                nonlocal sent
                body = command(sent)
                sent += 1
                if way == "bare":
                    payload = json.dumps({**body, "client": "bench-bare"}).encode()
                    started = time.perf_counter()
                    bare_get(bare, payload)
                elif way == "sync":
                    started = time.perf_counter()
                    device.send(body)
                else:
                    started = time.perf_counter()
                    await adevice.send(body)
                return time.perf_counter() - started

            ways = list(times)
            for round_ in range(WARMUP + count):
                order = ways[round_ % 3 :] + ways[: round_ % 3]
                for way in order:
                    elapsed = await one(way)
                    if round_ >= WARMUP:
                        times[way].append(elapsed)
    finally:
        client.close()
        bare.close()
    return times


def put_loop(put: Callable[[], None], seconds: float) -> tuple[int, float, float]:
    """Call ``put`` for ``seconds``: (calls, wall seconds, CPU seconds of this process)."""
    calls, cpu, started = 0, time.process_time(), time.perf_counter()
    end = started + seconds
    while time.perf_counter() < end:
        for _ in range(64):
            put()
        calls += 64
    return calls, time.perf_counter() - started, time.process_time() - cpu


def follow_rate(
    endpoint: str, seconds: float
) -> tuple[dict[str, tuple[int, float, float]], float, float]:
    """(calls, wall s, CPU s) of each way, interleaved in slices of ``SLICE_S``; the SDK's
    puts per second (``Follow.set`` spaces them 10 ms apart at least); and how long the
    gateway then took to answer again (``drained``)."""
    totals = {"SDK Follow.set": [0, 0.0, 0.0], "bare session.put": [0, 0.0, 0.0],
              "bare publisher.put": [0, 0.0, 0.0]}  # fmt: skip
    bare = zenoh.open(session_config(mode="client", connect=[endpoint]))
    publisher = bare.declare_publisher(FOLLOW_KEY, express=True)  # as Core.publisher declares it
    client = bc.connect(endpoint, client_id="bench-follow", timeout=TIMEOUT_S)
    payload = json.dumps({**FOLLOW_TARGET, "client": client.client_id}).encode()
    try:
        la1 = client.device(DEVICE)
        with la1.claim(), la1.follow() as f:
            puts = {
                "SDK Follow.set": functools.partial(f.set, **FOLLOW_TARGET),
                "bare session.put": functools.partial(bare.put, FOLLOW_KEY, payload),
                "bare publisher.put": functools.partial(publisher.put, payload),
            }
            for _ in range(max(1, round(seconds / SLICE_S))):
                for way, put in puts.items():
                    for i, figure in enumerate(put_loop(put, SLICE_S)):
                        totals[way][i] += figure
            sent_per_s = f.sent / totals["SDK Follow.set"][1]
            drain_s = drained(client, bare)  # before the exit: its end_follow queues behind
    finally:
        publisher.undeclare()
        client.close()
        bare.close()
    rates = {way: (int(n), wall, cpu) for way, (n, wall, cpu) in totals.items()}
    return rates, sent_per_s, drain_s


def drained(client: bc.Client, bare: zenoh.Session | None = None) -> float:
    """Seconds until the gateway answers an info query of ``client`` (and of ``bare``): each
    waits behind the puts still queued on its own session."""
    started = time.perf_counter()
    if not client.gateways(timeout=DRAIN_S):
        raise RuntimeError(f"the gateway did not answer within {DRAIN_S:g} s")
    if bare is not None:
        list(bare.get("busgate/demo/info", timeout=DRAIN_S))
    return time.perf_counter() - started


def claim_under_sets(endpoint: str, seconds: float) -> tuple[float | None, int, float]:
    """Seconds until a claim of the default TTL (2 s) is lost under a tight loop of sets
    (``None``: held for ``seconds``), the sets sent, and the seconds from the last set until
    the gateway answers this client again."""
    with bc.connect(endpoint, client_id="bench-claim", timeout=TIMEOUT_S) as client:
        la1 = client.device(DEVICE)
        lost, sets = None, 0
        started = time.perf_counter()
        try:
            with la1.claim(), la1.follow() as f:
                try:
                    while time.perf_counter() < started + seconds:
                        f.set(**FOLLOW_TARGET)
                        sets += 1
                except bc.ClaimLostError:
                    lost = time.perf_counter() - started
                stopped = time.perf_counter()
                drained(client)  # before the exit: its end_follow and release queue behind
        except bc.ClaimLostError:  # the claim block's exit reports the loss again
            if lost is None:  # lost after the loop, while the gateway caught up
                lost = time.perf_counter() - started
        return lost, sets, time.perf_counter() - stopped


async def connect_times(endpoint: str) -> dict[str, list[tuple[float, float]]]:
    """(connect s, connect → first device() s) of each face, ``CONNECTS`` times."""
    times: dict[str, list[tuple[float, float]]] = {"sync": [], "aio": []}
    for i in range(CONNECTS):
        started = time.perf_counter()
        client = bc.connect(endpoint, client_id=f"bench-connect-{i}")
        opened = time.perf_counter()
        client.device(DEVICE)
        times["sync"].append((opened - started, time.perf_counter() - started))
        client.close()
        started = time.perf_counter()
        aclient = await bc.aio.connect(endpoint, client_id=f"bench-aconnect-{i}")
        opened = time.perf_counter()
        await aclient.device(DEVICE)
        times["aio"].append((opened - started, time.perf_counter() - started))
        await aclient.close()
    return times


def profile(endpoint: str, op: str, count: int, seconds: float) -> None:
    """cProfile's top functions of ``count`` sends and ``seconds`` of sets, on this thread."""
    command = commands(op)
    with bc.connect(endpoint, client_id="bench-profile", timeout=TIMEOUT_S) as client:
        la1 = client.device(DEVICE)
        sends = cProfile.Profile()
        for i in range(count):
            sends.runcall(la1.send, command(i))
        print(f"\ncProfile of {count} Device.send({command(0)}), this thread, by own time:")
        pstats.Stats(sends).sort_stats("tottime").print_stats(14)
        with la1.claim(), la1.follow() as f:
            sets = cProfile.Profile()
            sets.runcall(put_loop, functools.partial(f.set, **FOLLOW_TARGET), seconds)
            drained(client)
        print(f"cProfile of {seconds:g} s of Follow.set(position=1000), by own time:")
        pstats.Stats(sets).sort_stats("tottime").print_stats(14)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=500, help="commands of each way")
    parser.add_argument("--seconds", type=float, default=2.0, help="follow puts of each way")
    parser.add_argument("--op", choices=["status", "release", "move"], default="status")
    parser.add_argument("--profile", action="store_true", help="cProfile send and set too")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        endpoint = free_endpoint()
        demo = Demo(Path(scratch), endpoint)
        try:
            connects = asyncio.run(connect_times(endpoint))
            times = asyncio.run(latency(endpoint, args.op, args.count))
            rates, sent_per_s, drain_s = follow_rate(endpoint, args.seconds)
            lost, lost_sets, lost_drain_s = claim_under_sets(endpoint, CLAIM_WATCH_S)
            if args.profile:
                profile(endpoint, args.op, args.count, args.seconds)
        finally:
            demo.stop()

    print(f"{args.count} × {commands(args.op)(0)} on {DEVICE}, interleaved    p50 µs   p99 µs")
    times["sync − bare"] = [s - b for s, b in zip(times["sync"], times["bare"], strict=True)]
    times["aio − bare"] = [a - b for a, b in zip(times["aio"], times["bare"], strict=True)]
    names = {"bare": "bare zenoh get", "sync": "SDK Device.send", "aio": "SDK aio Device.send"}
    for way, values in times.items():
        print(f"  {names.get(way, way):42} {us(values, 0.5):8} {us(values, 0.99):8}")
    print(f"follow puts, {args.seconds:g} s each in {SLICE_S:g} s slices      sets/s   CPU µs/set")
    for way, (n, wall, cpu) in rates.items():
        print(f"  {way:42} {n / wall:8.0f} {cpu / n * 1e6:8.2f}")
    print(f"  {'SDK puts sent (at most one per 10 ms)':42} {sent_per_s:8.0f}")
    print(f"  {'gateway answers again after':42} {drain_s:8.2f} s")
    held = f"lost after {lost:.1f} s" if lost is not None else f"held {CLAIM_WATCH_S:g} s"
    print(
        f"  {'claim (TTL 2 s) under a tight loop of sets':42} {held} ({lost_sets} sets; "
        f"the gateway answers again {lost_drain_s:.2f} s after the last)"
    )
    print(f"bc.connect, {CONNECTS} times (median ms)        open    → device()")
    for face, pairs in connects.items():
        opened, found = (statistics.median(p[i] for p in pairs) * 1000 for i in (0, 1))
        print(f"  {face + ' face':42} {opened:8.1f} {found:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
