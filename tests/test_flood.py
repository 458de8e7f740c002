"""A flood over zenoh: four clients send 300 moves each, as fast as replies come,
while a third actuator on the same bus follows a streamed target.

The gateway is ``busgate run`` in its own process, so its memory and file descriptors can be
read from /proc and the flood does not share its GIL; the simulator is another process and
records every frame it receives. What must hold exactly is asserted exactly: every get is
answered once, ``ok`` or ``busy`` (or ``device_timeout`` once the move went out as often as
the retry rule says: a simulator held up by a loaded machine answers late, and that is not the
gateway's doing); the gateway never starts a follow tick early; the follow
stream keeps its slot, counted in frames rather than per second: in the order the device
received them, no more of the flood's moves come between two of la3's ticks than fit in one
follow period, whatever the machine's speed. Memory gets room for the allocator.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from busgate.codecs.timing import uart_time
from busgate.gateway.scheduler.planner import MAX_RETRIES
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.recorder import WireRecord
from busgate.gateway.sim.wire_analysis import load_records
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.zenoh_session import MAX_RECEIVED, session_config

GATEWAY, BUS = "flood", "uart0"
CLIENTS, COMMANDS_EACH = 4, 300
FOLLOW_PERIOD_S = 0.020
FOLLOW_PUT_EVERY_S = 0.005
#: Longer than the gateway's own guard (``REPLY_TIMEOUT_S``), which answers first.
GET_TIMEOUT_S = 15.0
#: Growth of the gateway's resident memory the flood may cause. Its queues are bounded (64
#: commands, the state and event backlogs) and an answered query is let go at once (its
#: reply-timeout guard is cancelled): a 1,200-command flood grew RSS by about 0.4 MB
#: (measured), the allocator's pools warming up. A leak of 2 KB per command fails. (Before the
#: guard was cancelled, each query was held for 10 s: +3.7 MB.)
RSS_GROWTH_LIMIT_KB = 2 * 1024
#: How often a move goes out before it is answered ``device_timeout`` (idempotent: retried).
ATTEMPTS = MAX_RETRIES + 1
#: The most moves that fit between two follow ticks: a move starts only if it is over before
#: the next tick is due, and none is shorter than its frame, the reply and the gap after it.
MOVES_PER_PERIOD = math.ceil(FOLLOW_PERIOD_S / (
    PROTOCOLS["inspire_la"].timing.default_gap_s + uart_time(9 + la.STATUS_REPLY_SIZE, 921_600)))


@dataclass(frozen=True, slots=True)
class Answer:
    frame: str  # the move's frame as hex; positions are unique in the flood, so frames are too
    outcome: str  # "ok", the error code, or what went wrong with the get itself


@dataclass(frozen=True, slots=True)
class Flood:
    answers: list[Answer]
    seconds: float
    wall: tuple[float, float]  # wall clock at its start and end, as events are stamped
    rss_growth_kb: int
    fds: tuple[int, int]  # before, after
    stats: tuple[dict, dict]  # the bus's statistics before and after


def gateway_toml(endpoint: str, port: str) -> str:
    devices = "".join(
        f'[[buses.devices]]\nname = "la{i}"\nkind = "inspire_la"\nid = {i}\n'
        f"follow_period_ms = {FOLLOW_PERIOD_S * 1000:.0f}\n"
        for i in (1, 2, 3)
    )
    return (f'[gateway]\nname = "{GATEWAY}"\n[zenoh]\nlisten = ["{endpoint}"]\n'
            f'[[buses]]\nname = "{BUS}"\ntransport = "serial"\nport = "{port}"\n'
            f"baudrate = 921600\n{devices}")


def resident_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as status:
        line = next(line for line in status if line.startswith("VmRSS:"))
    return int(line.split()[1])


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def device_states(session: zenoh.Session) -> list[dict]:
    for reply in session.get(f"busgate/{GATEWAY}/info", timeout=1):
        if reply.ok:
            info = json.loads(reply.ok.payload.to_bytes())
            return [d["state"] or {} for bus in info["buses"] for d in bus["devices"]]
    return []


def outcome(replies: list[zenoh.Reply]) -> str:
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok]
    if len(answers) != 1 or len(replies) != 1:
        return f"{len(answers)} answers in {len(replies)} replies"
    return "ok" if answers[0]["ok"] else answers[0]["error"]["code"]


def send_moves(session: zenoh.Session, client: int) -> list[Answer]:
    """One client's moves, each sent when the previous one is answered, la1 and la2 in turn."""
    answers = []
    for i in range(COMMANDS_EACH):
        device_id, position = 1 + i % 2, client * COMMANDS_EACH + i
        move = json.dumps({"op": "move", "position": position})
        replies = session.get(f"busgate/{GATEWAY}/dev/la{device_id}/cmd", payload=move,
                              timeout=GET_TIMEOUT_S)
        frame = la.encode(la.MoveCommand(device_id, position)).hex()
        answers.append(Answer(frame, outcome(list(replies))))
    return answers


def stream_la3(session: zenoh.Session, stop: threading.Event) -> None:
    """la3's follow target, a new one every ``FOLLOW_PUT_EVERY_S`` until ``stop``."""
    key, tick = f"busgate/{GATEWAY}/dev/la3/follow", 0
    while not stop.wait(FOLLOW_PUT_EVERY_S):
        tick += 1
        session.put(key, json.dumps({"position": 500 + tick % 200}))


def run_flood(pid: int, clients: list[zenoh.Session], stats: list[dict], wait_for) -> Flood:
    """The four clients' moves at once, with the gateway's memory, descriptors and bus
    statistics (published once a second) from before and after."""
    wait_for(lambda: stats and stats[-1]["follow_intervals"] > 0)
    before, rss_before, fds_before = stats[-1], resident_kb(pid), open_fds(pid)
    started, started_wall = time.perf_counter(), time.time()
    with ThreadPoolExecutor(CLIENTS) as pool:
        answers = [a for each in pool.map(send_moves, clients, range(CLIENTS)) for a in each]
    seconds, ended_wall = time.perf_counter() - started, time.time()
    rss_growth, fds_after = resident_kb(pid) - rss_before, open_fds(pid)
    wait_for(lambda: stats[-1]["ts"] > ended_wall, timeout=20)
    return Flood(answers, seconds, (started_wall, ended_wall), rss_growth,
                 (fds_before, fds_after), (before, stats[-1]))


def moves_between_ticks(records: list[WireRecord], moves: set[str]) -> list[int]:
    """How many of ``moves`` (frames as hex) the device received before la3's first tick,
    between each two ticks and after the last, in the order it received them."""
    runs, run = [], 0
    for record in records:
        if record.direction != "rx":
            continue
        if record.frame == "FollowCommand" and record.device_id == 3:
            runs.append(run)
            run = 0
        elif record.wire in moves:
            run += 1
    return [*runs, run]


def unexplained(answers: list[Answer], records: list[WireRecord]) -> dict[str, list[int]]:
    """Each outcome other than ok, busy and a timeout the gateway earned by its retry rule,
    with how often each such move reached the device. A ``device_timeout`` is the right answer
    once the move went out ``ATTEMPTS`` times without a reply in its window: the simulator,
    on the same cores as the gateway, the flood and whatever else runs, can be late, and how
    late is not for this test to judge. Anything else (another code, no answer, a timeout
    after fewer attempts or more) is the gateway's."""
    received = Counter(r.wire for r in records if r.direction == "rx")
    found: dict[str, list[int]] = {}
    for answer in answers:
        earned = answer.outcome == "device_timeout" and received[answer.frame] == ATTEMPTS
        if answer.outcome not in ("ok", "busy") and not earned:
            found.setdefault(answer.outcome, []).append(received[answer.frame])
    return found


@pytest.fixture
def gateway(tmp_path: Path, free_port, wait_for):
    """The simulator and ``busgate run``, both up with every device online; yields the
    gateway's process, its endpoint, an observer session and the wire record's path."""
    record = tmp_path / "wire.jsonl"
    simulator = SimProcess("inspire_la", ["--ids", "1,2,3", "--busy-poll-ms", "0",
                                          "--record", str(record)])
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "gw.toml"
    config.write_text(gateway_toml(endpoint, simulator.port))
    with open(tmp_path / "gateway.log", "w") as log:
        process = subprocess.Popen([sys.executable, "-m", "busgate.gateway.cli", "run",
                                    "--config", str(config), "--log-level", "warning"],
                                   stderr=log)
    observer = zenoh.open(session_config(connect=[endpoint]))
    try:
        wait_for(lambda: [s.get("online") for s in device_states(observer)] == [True] * 3,
                 timeout=20)
        yield process, endpoint, observer, record
    finally:
        observer.close()
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        simulator.stop()


def test_a_flood_over_zenoh_is_answered_bounded_and_keeps_the_follow_stream(
    gateway, wait_for
) -> None:
    process, endpoint, observer, record = gateway
    stats: list[dict] = []
    subscriber = observer.declare_subscriber(
        f"busgate/{GATEWAY}/bus/{BUS}/stats",
        lambda sample: stats.append(json.loads(sample.payload.to_bytes())))
    events: list[dict] = []
    event_subscriber = observer.declare_subscriber(
        f"busgate/{GATEWAY}/dev/la3/event",
        lambda sample: events.append(json.loads(sample.payload.to_bytes())))
    clients = [zenoh.open(session_config(connect=[endpoint])) for _ in range(CLIENTS)]
    stop_streaming = threading.Event()
    streamer = threading.Thread(target=stream_la3, args=(observer, stop_streaming))
    streamer.start()
    try:
        flood = run_flood(process.pid, clients, stats, wait_for)
    finally:
        stop_streaming.set()
        streamer.join()
        subscriber.undeclare()
        event_subscriber.undeclare()
        for client in clients:
            client.close()

    records = load_records(record)
    outcomes = Counter(answer.outcome for answer in flood.answers)
    before, after = flood.stats
    runs = moves_between_ticks(records, {answer.frame for answer in flood.answers})
    # A client held up for longer than a stream's freshness lets it go stale (reported); the
    # next target starts it again. Only such a gap may hold more moves than a period's worth.
    stale = [e for e in events if e["type"] == "stream_stale"]
    crowded = [n for n in runs if n > MOVES_PER_PERIOD]
    print(f"{dict(outcomes)} in {flood.seconds:.2f} s; RSS +{flood.rss_growth_kb} kB; "
          f"fds {flood.fds}; la3: {len(runs) - 1} ticks, at most {max(runs)} moves between two "
          f"(bound {MOVES_PER_PERIOD}), {len(stale)} stale; host side: "
          f"{after['follow_intervals'] - before['follow_intervals']} intervals, "
          f"smallest error {after['follow_error_min_s']:.6f} s")

    surprises = unexplained(flood.answers, records)
    assert len(flood.answers) == CLIENTS * COMMANDS_EACH
    assert not surprises, f"outcome: [times each such move reached the device] {surprises}"
    assert outcomes["ok"] > 0
    assert after["busy_commands"] - before["busy_commands"] == outcomes["busy"]
    assert flood.rss_growth_kb < RSS_GROWTH_LIMIT_KB
    assert abs(flood.fds[1] - flood.fds[0]) <= 2
    assert after["follow_error_min_s"] >= 0, "a follow interval shorter than the period"
    assert after["follow_intervals"] > before["follow_intervals"], "the stream ran meanwhile"
    assert len(crowded) <= len(stale), f"moves held la3's ticks back: {crowded}"


#: A hostile client's get: a command padded to just under the session's largest message, as
#: fast as zenoh takes it (``BLOCK``), until killed.
LARGE_GETS = """
import sys, zenoh
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.zenoh_session import MAX_RECEIVED, session_config
endpoint, key, size = sys.argv[1], sys.argv[2], int(sys.argv[3])
session = zenoh.open(session_config(mode="client", connect=[endpoint]))
payload = (b'{"op": "status", "pad": "' + b"x" * size)[: size - 2] + b'"}'
while True:
    session.get(key, lambda reply: None, payload=payload, timeout=1.0,
                congestion_control=zenoh.CongestionControl.BLOCK)
"""
#: How much the gateway's memory may grow under four clients' 2 MiB gets. Each is refused
#: ``too_large`` by its size, unread, as fast as it comes: the demo grew 21 MB in 20 s of it
#: (measured). Copied out of zenoh first, they were handled slower than they came, and
#: zenoh's ring held what waited: 5.3 GB in 20 s.
LARGE_FLOOD_RSS_LIMIT_KB = 256 * 1024


@pytest.mark.slow
def test_a_flood_of_gets_of_the_largest_message_is_refused_unread_and_holds_no_memory(
    gateway, wait_for
):
    process, endpoint, observer, _ = gateway
    size = MAX_RECEIVED - 4096
    before = resident_kb(process.pid)
    floods = [subprocess.Popen([sys.executable, "-c", LARGE_GETS, endpoint,
                                f"busgate/{GATEWAY}/dev/la1/cmd", str(size)])
              for _ in range(CLIENTS)]
    peak, deadline = before, time.monotonic() + 8.0
    try:
        while time.monotonic() < deadline:
            peak = max(peak, resident_kb(process.pid))
            time.sleep(0.25)
    finally:
        for flood in floods:
            flood.kill()
            flood.wait()
    assert peak - before < LARGE_FLOOD_RSS_LIMIT_KB, f"{(peak - before) // 1024} MiB more"
    [reply] = observer.get(f"busgate/{GATEWAY}/dev/la1/cmd", payload=b"x" * (MAX_PAYLOAD + 1),
                           timeout=5)
    assert json.loads(reply.ok.payload.to_bytes())["error"] == {"code": "too_large", "message": (
        f"payload of {MAX_PAYLOAD + 1} bytes; at most {MAX_PAYLOAD}")}
    wait_for(lambda: [s.get("online") for s in device_states(observer)] == [True] * 3)

