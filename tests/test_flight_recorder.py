"""The flight recorder's pieces without a daemon: the ring (forgets by age and by count, a
snapshot taken while other threads append loses and repeats nothing), what triggers an
incident, the incident file read back with the ``mcap`` library (every channel its schema,
every message valid against it, times in order, the triggers in its metadata), pruning to
the size budget, coalescing triggers, and the folder checks that refuse a recorder that could
not write."""

from __future__ import annotations

import asyncio
import errno
import gc
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from mcap.reader import make_reader

from busgate.errors import BusgateError
from busgate.gateway.bus.clock import now
from busgate.gateway.recording import flight, incident_file
from busgate.gateway.recording.flight import FlightRecorder, Trigger, folder_problem, trigger_of
from busgate.gateway.recording.ring import CHUNK, Ring
from busgate.schemas.config import RecorderSection
from busgate.schemas.events import BUS_DOWN_REASON, WORKER_ENDED_REASON
from tests.conftest import may_run_realtime
from tests.test_schema_export import assert_valid, inspire_la_state

BUSES = {"uart0": ["la1", "la2"], "can0": ["wheel"]}


# --- the ring -------------------------------------------------------------------------------


def since(ring: Ring, start: float) -> list[tuple]:
    """The ring's entries from ``start`` on, as the incident writer takes them."""
    return [entry for chunk in ring.chunks(start) for entry in chunk if entry[0] >= start]


def test_the_ring_forgets_what_is_older_than_its_seconds() -> None:
    ring = Ring(seconds=1.0, max_entries=10**6, max_bytes=10**9)
    for n in range(CHUNK * 10):
        ring.append((n * 0.01, n, b""))  # 100 entries a second, 25.6 s in all
    kept = since(ring, 0.0)
    newest = kept[-1][0]
    assert kept[-1][1] == CHUNK * 10 - 1
    assert [n for _, n, _ in kept] == list(range(kept[0][1], CHUNK * 10))  # none lost between
    assert newest - kept[0][0] <= 1.0 + CHUNK * 0.01  # at most a chunk beyond its seconds
    assert len(ring) == len(kept)


def test_the_ring_holds_at_most_its_entries_whatever_the_rate() -> None:
    ring = Ring(seconds=1e9, max_entries=CHUNK * 4, max_bytes=10**9)
    for n in range(CHUNK * 100):
        ring.append((0.0, n, b""))
    assert CHUNK * 4 <= len(ring) <= CHUNK * 5
    assert since(ring, 0.0)[-1] == (0.0, CHUNK * 100 - 1, b"")


def test_the_ring_holds_at_most_its_bytes_whatever_a_peer_sends() -> None:
    ring = Ring(seconds=1e9, max_entries=10**6, max_bytes=1_000_000)
    for n in range(2000):
        ring.append((float(n), n, bytes(10_000)))  # 20 MB in all, in a few entries
    kept = since(ring, 0.0)
    held = sum(len(data) for _, _, data in kept)
    assert 1_000_000 - 10_000 * 16 < held <= 1_000_000 + 1_000_000 // 16 + 10_000
    assert kept[-1][1] == 1999 and [n for _, n, _ in kept] == list(range(kept[0][1], 2000))


def test_since_leaves_out_what_came_before_it() -> None:
    ring = Ring(seconds=100.0, max_entries=10**6, max_bytes=10**9)
    for n in range(1000):
        ring.append((float(n), n, b""))
    assert [n for _, n, _ in since(ring, 990.0)] == list(range(990, 1000))


def test_a_snapshot_while_threads_append_loses_and_repeats_nothing() -> None:
    ring = Ring(seconds=1e9, max_entries=10**7, max_bytes=10**12)
    writers, per_writer = 4, 20_000
    seen: list[list[tuple]] = []
    done = threading.Event()

    def write(writer: int) -> None:
        for n in range(per_writer):
            ring.append((0.0, writer, b"", n))

    def read() -> None:
        while not done.is_set():
            seen.append(since(ring, 0.0))

    reader = threading.Thread(target=read)
    threads = [threading.Thread(target=write, args=(w,)) for w in range(writers)]
    reader.start()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    done.set()
    reader.join()
    seen.append(since(ring, 0.0))
    for snapshot in seen:
        for writer in range(writers):
            numbers = [n for _, w, _, n in snapshot if w == writer]
            assert numbers == list(range(len(numbers)))  # each writer's, in order, no gap
    assert len(seen[-1]) == writers * per_writer


def test_what_the_rings_hold_is_nothing_the_garbage_collector_walks(tmp_path) -> None:
    """A minute of 20 devices is near a million entries: were they objects the collector
    tracks, each full collection would walk them all, stopping every thread (bus ones too)."""
    made = recorder(tmp_path)
    feed(made, count=3)
    gc.collect()
    rings = [made.published, made.commands, *made.frames.values()]
    entries = [entry for ring in rings for entry in since(ring, 0.0)]
    assert len(entries) == 3 * 5 + 4  # 5 each round, and the 4 commands after
    assert not any(gc.is_tracked(entry) for entry in entries)


# --- what triggers an incident -----------------------------------------------------------------


BUS_OF = {"la1": "uart0", "wheel": "can0"}


@pytest.mark.parametrize(
    ("event", "slug"),
    [
        ({"type": "estop", "device": "*", "key": "busgate/gw/estop"}, "estop"),
        ({"type": "estop", "device": "*", "client": "teleop"}, "estop"),
        ({"type": "fault", "device": "la1", "faults": ["overheat"], "raised": ["overheat"],
          "cleared": []}, "fault-la1"),
        ({"type": "offline", "device": "wheel", "reason": BUS_DOWN_REASON}, "bus-down-can0"),
        ({"type": "offline", "device": "la1", "reason": f"{WORKER_ENDED_REASON} (killed by "
          "SIGKILL)"}, "worker-ended-uart0"),
    ],
)
def test_these_events_trigger_an_incident(event, slug) -> None:
    found = trigger_of(event, BUS_OF)
    assert found is not None and found.slug == slug
    if event.get("client"):
        assert "teleop" in found.text


@pytest.mark.parametrize(
    "event",
    [
        {"type": "fault", "device": "la1", "faults": [], "raised": [], "cleared": ["overheat"]},
        {"type": "offline", "device": "la1", "reason": "no reply"},
        {"type": "online", "device": "la1"},
        {"type": "claimed", "device": "la1", "client": "a", "ttl_s": 2.0},
        {"type": ["estop"]},
        {},
    ],
)
def test_other_events_do_not(event) -> None:
    assert trigger_of(event, BUS_OF) is None


# --- an incident file --------------------------------------------------------------------------


def recorder(tmp_path: Path, **settings) -> FlightRecorder:
    made = FlightRecorder(
        RecorderSection(dir=str(tmp_path), **settings),
        prefix="busgate",
        gateway="gw",
        buses=BUSES,
        version="test",
    )
    made.prepare()
    return made


def state(device: str, position: int) -> dict:
    """A state as an Inspire LA driver publishes it (checked against its schema in the file)."""
    return inspire_la_state() | {"device": device, "position": position}


def feed(made: FlightRecorder, count: int = 20) -> None:
    """``count`` rounds of what a gateway hands its recorder: a state, a command, frames."""
    tap_uart, tap_can = made.tap("uart0"), made.tap("can0")
    for n in range(count):
        body = state("la1", n)
        made.on_published("busgate/gw/dev/la1/state", body, json.dumps(body).encode())
        command = {"op": "move", "position": n, "client": "teleop"}
        made.on_command("busgate/gw/dev/la1/cmd", json.dumps(command).encode(), {"ok": True})
        tap_uart((now(), "tx", bytes([0x55, 0xAA, n]), None))
        tap_uart((now(), "rx", bytes([0xAA, 0x55, n]), None))
        tap_can((now(), "tx", bytes([n]), 0x601))
    made.on_command("busgate/gw/dev/la1/cmd", b"\xff not json", {"ok": False, "error": {
        "code": "not_utf8", "message": "no"}})
    made.on_command("busgate/gw/dev/la1/cmd", b'{"op":"move","position":NaN,"client":"no spaces"}',
                    {"ok": False, "error": {"code": "not_json", "message": "NaN"}})
    made.on_command("busgate/gw/dev/la1/cmd", b'{"op":"claim","client":"not a valid id!"}',
                    {"ok": False, "error": {"code": "bad_command", "message": "client"}})
    made.on_command("busgate/gw/estop", b"", None)


def read(path: Path):
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        messages = [(schema, channel.topic, message) for schema, channel, message
                    in reader.iter_messages(log_time_order=False)]
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return summary, messages, metadata


def test_an_incident_file_holds_every_channel_with_its_schema_in_order(tmp_path) -> None:
    made = recorder(tmp_path)
    feed(made)
    path = made.write_incident([Trigger("estop", "e-stop from teleop")], now())
    assert path.parent == tmp_path and path.name.startswith("incident-gw-")
    assert path.name.endswith("-estop.mcap") and not list(tmp_path.glob("*.part"))
    summary, messages, metadata = read(path)
    topics = {channel.topic: summary.schemas.get(channel.schema_id)
              for channel in summary.channels.values()}
    assert {topic: schema.name if schema else None for topic, schema in topics.items()} == {
        "busgate/gw/dev/la1/state": "telemetry.inspire_la",
        "busgate/gw/commands": "recorded_command",
        "busgate/gw/bus/uart0/frames": "frame",
        "busgate/gw/bus/can0/frames": "frame",
    }
    assert all(schema.encoding == "jsonschema" for schema in topics.values())
    counts = {}
    for schema, topic, message in messages:
        counts[topic] = counts.get(topic, 0) + 1
        assert_valid(f"{schema.name}.json", json.loads(message.data))
    assert counts == {"busgate/gw/dev/la1/state": 20, "busgate/gw/commands": 24,
                      "busgate/gw/bus/uart0/frames": 40, "busgate/gw/bus/can0/frames": 20}
    times = [message.log_time for _, _, message in messages]
    assert times == sorted(times)  # written in time order
    assert metadata["incident"]["triggers"] == "e-stop from teleop"
    assert metadata["incident"]["gateway"] == "gw"


@pytest.mark.skipif(not may_run_realtime(), reason="SCHED_FIFO is not allowed here")
def test_the_writer_started_by_a_real_time_daemon_runs_at_normal_priority(tmp_path) -> None:
    """Rule 3 of ``incident_file``: started from a ``SCHED_FIFO`` thread (a daemon whose
    buses ask for real-time priority), it leaves that priority before it reads a thing."""
    launch = (
        "import os, sys; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10)); "
        "os.execv(sys.executable, [sys.executable, '-m', sys.argv[1], sys.argv[2]])"
    )
    writer = subprocess.Popen(
        [sys.executable, "-c", launch, flight.WRITER, str(tmp_path / "out.mcap")],
        stdin=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )

    def scheduling() -> tuple[int, int]:
        return os.sched_getscheduler(writer.pid), os.getpriority(os.PRIO_PROCESS, writer.pid)

    try:
        deadline = time.monotonic() + 10  # until it has niced itself, which comes last
        while time.monotonic() < deadline and writer.poll() is None:
            if scheduling()[1] >= incident_file.NICENESS:
                break
            time.sleep(0.01)
        assert scheduling() == (os.SCHED_OTHER, incident_file.NICENESS)
    finally:
        writer.stdin.close()  # no snapshot: it ends, saying so
        writer.wait(10)


def test_frames_and_commands_read_back_as_they_were(tmp_path) -> None:
    made = recorder(tmp_path)
    feed(made, count=3)
    _, messages, _ = read(made.write_incident([Trigger("signal", "SIGUSR1")], now()))
    bodies = [(topic, json.loads(m.data)) for _, topic, m in messages]
    uart = [body for topic, body in bodies if topic.endswith("uart0/frames")]
    assert [(b["dir"], b["wire"]) for b in uart[:2]] == [("tx", "55aa00"), ("rx", "aa5500")]
    can = [body["wire"] for topic, body in bodies if topic.endswith("can0/frames")]
    assert can == ["601#00", "601#01", "601#02"]
    commands = [body for topic, body in bodies if topic.endswith("/commands")]
    assert commands[0]["client"] == "teleop" and commands[0]["command"]["position"] == 0
    assert commands[0]["code"] == "ok"
    refused = commands[-4]
    assert refused["command"] is None and refused["text"].endswith("not json")
    assert refused["code"] == "not_utf8"
    nan, bad_client = commands[-3], commands[-2]  # what no schema allows is not passed on
    assert nan["command"] is None and "NaN" in nan["text"] and nan["client"] is None
    assert bad_client["command"]["op"] == "claim" and bad_client["client"] is None
    assert commands[-1]["key"] == "busgate/gw/estop" and commands[-1]["code"] == "ok"


def test_only_the_last_seconds_go_into_the_file(tmp_path) -> None:
    made = recorder(tmp_path, seconds=1.0)
    tap = made.tap("uart0")
    at = now()
    tap((at - 5.0, "tx", b"\x01", None))  # long before: left out
    tap((at - 0.5, "tx", b"\x02", None))
    _, messages, _ = read(made.write_incident([Trigger("signal", "SIGUSR1")], at))
    assert [json.loads(m.data)["wire"] for _, _, m in messages] == ["02"]


def old_incidents(folder: Path) -> list[Path]:
    """Three incident files of 400 kB in ``folder``, oldest first."""
    old = []
    for n in range(3):
        path = folder / f"incident-gw-2026010{n}T000000.000Z-estop.mcap"
        path.write_bytes(b"x" * 400_000)
        os.utime(path, (1_000_000 + n, 1_000_000 + n))
        old.append(path)
    return old


def test_old_incidents_are_pruned_to_the_budget_and_the_new_one_stays(tmp_path) -> None:
    made = recorder(tmp_path, max_total_mb=1)
    old = old_incidents(tmp_path)
    unrelated = tmp_path / "notes.txt"
    unrelated.write_bytes(b"y" * 2_000_000)
    made.trigger(Trigger("signal", "SIGUSR1"))
    newest = made.write_pending()
    assert newest is not None and newest.exists()
    assert [path.exists() for path in old] == [False, True, True]  # 1 MiB: two of 400 kB left
    assert unrelated.exists()  # only incident files are the recorder's


def test_a_disk_with_no_room_for_an_incident_loses_the_oldest_not_the_newest(
        tmp_path, monkeypatch) -> None:
    """An audit: on a full disk the newest incident (the e-stop's, say) failed and the oldest
    stayed, for good. A write that fails on a disk with less room than the largest incident
    there takes the oldest away until there is, and is written again. (The disk is a stand-in:
    100 kB free and what each file taken away frees.)"""
    made = recorder(tmp_path)
    old = old_incidents(tmp_path)
    freed = lambda: 100_000 + 400_000 * sum(not p.exists() for p in old)  # noqa: E731
    monkeypatch.setattr(shutil, "disk_usage", lambda _: SimpleNamespace(free=freed()))
    write, tries = made.write_incident, []

    def full_once(*args):
        tries.append(args)
        if len(tries) == 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return write(*args)

    monkeypatch.setattr(made, "write_incident", full_once)
    made.trigger(Trigger("estop", "e-stop"))
    newest = made.write_pending()
    assert newest is not None and newest.exists() and len(tries) == 2
    assert [path.exists() for path in old] == [False, True, True]  # 500 kB free: room for one


def test_a_file_larger_than_the_budget_is_kept_alone(tmp_path) -> None:
    made = recorder(tmp_path, max_total_mb=1)
    earlier = tmp_path / "incident-gw-20260101T000000.000Z-estop.mcap"
    earlier.write_bytes(b"x" * 10)
    os.utime(earlier, (1_000_000, 1_000_000))
    tap = made.tap("uart0")
    for _ in range(20_000):
        tap((now(), "tx", os.urandom(32), None))  # what no compression makes smaller
    made.trigger(Trigger("signal", "SIGUSR1"))
    newest = made.write_pending()
    assert newest is not None and newest.stat().st_size > 1024 * 1024
    assert not earlier.exists()


def test_a_write_that_fails_is_logged_and_the_recorder_goes_on(tmp_path, caplog) -> None:
    made = recorder(tmp_path / "incidents")
    made.trigger(Trigger("estop", "e-stop"))
    (tmp_path / "incidents").rmdir()
    assert made.write_pending() is None
    assert "incident (e-stop) not written" in caplog.text
    made.prepare()
    made.trigger(Trigger("estop", "e-stop"))
    assert made.write_pending() is not None


def test_prepare_removes_what_a_crash_left_half_written(tmp_path) -> None:
    part = tmp_path / "incident-gw-20260101T000000.000Z-estop.mcap.part"
    part.write_bytes(b"half")
    recorder(tmp_path)
    assert not part.exists()


def test_a_folder_that_cannot_be_written_is_refused_in_one_line(tmp_path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    made = FlightRecorder(RecorderSection(dir=str(blocker / "incidents")), prefix="busgate",
                          gateway="gw", buses=BUSES, version="test")
    with pytest.raises(BusgateError, match=r"recorder: .*a-file is a file, not a folder \(the"):
        made.prepare()
    assert folder_problem(blocker / "incidents") == f"{blocker} is not a directory"
    assert folder_problem(tmp_path / "new" / "deeper") is None  # it can be made


# --- triggers coalesce -----------------------------------------------------------------------


def test_triggers_that_come_together_make_one_file_naming_them_all(tmp_path, monkeypatch):
    monkeypatch.setattr(flight, "AFTER_S", 0.1)
    monkeypatch.setattr(flight, "HOLDOFF_S", 2.0)
    made = recorder(tmp_path)
    feed(made, count=2)

    def incident_files(folder: Path) -> list[Path]:
        return sorted(folder.glob("incident-*.mcap"))  # the names begin with their time

    async def written(count: int) -> float:
        for _ in range(200):
            if len(incident_files(tmp_path)) >= count:
                return time.monotonic()
            await asyncio.sleep(0.05)
        raise AssertionError(f"{len(incident_files(tmp_path))} files, not {count}")

    async def scenario() -> None:
        stop = asyncio.Event()
        running = asyncio.create_task(made.run(stop))
        await asyncio.sleep(0.05)
        made.trigger(Trigger("estop", "e-stop"))
        made.trigger(Trigger("fault-la1", "fault on la1: overheat"))
        first = await written(1)
        made.trigger(Trigger("bus-down-uart0", "bus uart0 down"))  # within the hold-off
        made.trigger(Trigger("signal", "SIGUSR1"))
        second = await written(2)
        assert second - first >= 2.0
        made.trigger(Trigger("estop", "e-stop"))
        stop.set()  # pending at the stop: for flush, after the buses
        await running
        assert len(incident_files(tmp_path)) == 2
        await asyncio.to_thread(made.flush)
        assert len(incident_files(tmp_path)) == 3

    asyncio.run(scenario())
    triggers = [read(path)[2]["incident"]["triggers"] for path in incident_files(tmp_path)]
    assert triggers == ["e-stop; fault on la1: overheat", "bus uart0 down; SIGUSR1", "e-stop"]
    assert incident_files(tmp_path)[0].name.endswith("-estop.mcap")
    assert incident_files(tmp_path)[1].name.endswith("-bus-down-uart0.mcap")


def test_a_flood_of_triggers_names_each_once_and_at_most_so_many(tmp_path) -> None:
    made = recorder(tmp_path)
    for n in range(10_000):
        made.trigger(Trigger("estop", "e-stop"))
        made.trigger(Trigger(f"fault-d{n}", f"fault on d{n}: overheat"))
    path = made.write_pending()
    assert path is not None and path.name.endswith("-estop.mcap")
    named = read(path)[2]["incident"]["triggers"].split("; ")
    assert named[:2] == ["e-stop", "fault on d0: overheat"]
    assert len(named) == flight.TRIGGERS_NAMED == len(set(named))


def test_an_event_published_on_the_events_key_is_what_triggers(tmp_path) -> None:
    made = recorder(tmp_path)
    estop = {"ts": 1.0, "device": "*", "type": "estop", "key": "busgate/gw/estop"}
    made.on_published("busgate/gw/dev/la1/event", estop, json.dumps(estop).encode())
    assert made.write_pending() is None  # the device's copy of it: no trigger twice
    made.on_published("busgate/gw/events", estop, json.dumps(estop).encode())
    assert made.write_pending() is not None
