"""``busgate record`` and ``busgate replay`` as child processes against ``busgate demo``: the
file read back with the ``mcap`` library's own reader (a channel per key, each with its JSON
Schema, every message published while it recorded, times in order), SIGINT ending it with a
complete file, every refusal one line with exit status 2, and replay publishing the
telemetry again, in order and never early, and nothing on a command or e-stop key: under
``replay`` unless told otherwise, never outside the prefix it is given, and not under the
demo's own prefix (or under its keys) while the demo is live there, unless ``--onto-live``;
a disk refusing a write ending a recording in one line, and a hostile file (huge chunks,
messages or gaps, keys zenoh refuses) replayed within bounds, Ctrl-C stopping it cleanly."""

from __future__ import annotations

import errno
import io
import json
import os
import re
import signal
import socket
import struct
import subprocess
import threading
import time

import pytest
import zenoh
from mcap.reader import make_reader
from mcap.writer import Writer

import busgate.client as bc
from busgate.gateway.cli import main
from busgate.gateway.cli import record as record_command
from busgate.gateway.recording import mcap_log
from busgate.gateway.recording.mcap_log import McapLog, schema_name
from busgate.schemas.exported import generated
from busgate.schemas.payload import MAX_WHOLE_GATEWAY
from busgate.schemas.zenoh_session import session_config
from tests.gateway_process import BUSGATE, TIMEOUT_S, run_busgate

TEST_KEY = "busgate/rec-test/dev/x/state"
COUNT = 60
EVERY_S = 0.01


@pytest.fixture(scope="module")
def client(module_demo):
    with bc.connect(module_demo.endpoint, client_id="record-test") as c:
        yield c


def record(module_demo, path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([*BUSGATE, "record", "--connect", module_demo.endpoint, "-o",
                             str(path), *args], stderr=subprocess.PIPE, text=True)


def wait_recording(recorder: subprocess.Popen) -> str:
    """Its first line, once its subscriptions are declared."""
    line = recorder.stderr.readline()
    assert line.startswith("busgate record: recording "), line
    time.sleep(0.5)  # its subscriptions reached the demo
    return line


def publish_known(client) -> list[bytes]:
    """``COUNT`` states of a made-up device, ``EVERY_S`` apart, plus a command and an e-stop
    put under the prefix (what replay must never publish again)."""
    sent = []
    for n in range(COUNT):
        payload = json.dumps({"ts": time.time(), "device": "x", "kind": "inspire_la",
                              "n": n}).encode()
        client.put(TEST_KEY, payload)
        sent.append(payload)
        time.sleep(EVERY_S)
    client.put("busgate/rec-test/dev/x/cmd", {"op": "move", "position": 1})
    client.put("busgate/rec-test/estop", {"client": "record-test"})
    return sent


def replayed(client, heard_on: str, path, module_demo, *args: str):
    """``busgate replay FILE ARGS`` against the demo, and what was heard on the key expression
    ``heard_on`` meanwhile: (key, payload, arrival)."""
    heard: list[tuple[str, bytes, float]] = []
    end = client.subscribe_raw(heard_on,
                               lambda key, payload, ns: heard.append((key, payload,
                                                                      time.monotonic())))
    try:
        done = run_busgate("replay", str(path), "--connect", module_demo.endpoint, *args)
        time.sleep(0.5)
    finally:
        end()
    return done, heard


def live_refusal(prefix: str, gateways: str) -> str:
    """``busgate replay``'s one line for a ``--prefix`` where ``gateways`` are live."""
    return (f"busgate replay: error: --prefix {prefix} is live (gateway {gateways}): a replay "
            "there writes into its telemetry; use another --prefix (default replay) or add "
            "--onto-live")


@pytest.fixture(scope="module")
def recorded(module_demo, client, tmp_path_factory):
    path = tmp_path_factory.mktemp("record") / "demo.mcap"
    recorder = record(module_demo, path)
    try:
        line = wait_recording(recorder)
        assert line.rstrip() == f"busgate record: recording busgate/** to {path} until Ctrl-C"
        sent = publish_known(client)
        time.sleep(0.5)
    finally:
        recorder.send_signal(signal.SIGINT)
        _, stderr = recorder.communicate(timeout=TIMEOUT_S)
    assert recorder.returncode == 0, stderr
    return path, sent, stderr


def test_every_channel_has_its_key_and_schema_and_every_message_came(recorded) -> None:
    path, sent, stderr = recorded
    assert "0 dropped" in stderr.splitlines()[-1]
    texts = generated()
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None  # finished: indexed
        topics = {c.topic: c for c in summary.channels.values()}
        for topic, channel in topics.items():
            assert channel.message_encoding == "json"
            if topic.endswith(("/state", "/stats", "/events", "/event")):
                schema = summary.schemas[channel.schema_id]
                assert schema.encoding == "jsonschema"
                assert schema.data.decode() == texts[f"{schema.name}.json"], topic
        assert summary.schemas[topics["busgate/demo/dev/la1/state"].schema_id].name == (
            "telemetry.inspire_la")
        assert summary.schemas[topics["busgate/demo/bus/uart0/stats"].schema_id].name == (
            "bus_stats")
        assert topics["busgate/rec-test/estop"].schema_id == 0  # no schema for an e-stop
        ours = [(m.data, m.log_time, m.publish_time)
                for _, c, m in reader.iter_messages(topics=[TEST_KEY], log_time_order=False)]
    assert [data for data, _, _ in ours] == sent
    log_times = [log for _, log, _ in ours]
    assert log_times == sorted(log_times)
    for data, _, published in ours:
        assert published == int(json.loads(data)["ts"] * 1e9)


@pytest.mark.parametrize(("tail", "body", "schema"), [
    ("dev/la1/state", {"kind": "inspire_la"}, "telemetry.inspire_la.json"),
    ("dev/la1/state", {"kind": "no such kind"}, None),
    ("dev/la1/event", {}, "event.json"),
    ("events", {}, "event.json"),
    ("bus/can0/stats", {}, "bus_stats.json"),
    ("bus/can0/frames", {}, "frame.json"),
    ("commands", {}, "recorded_command.json"),
    ("joints", {}, "joints.json"),
    ("base/base/odom", {}, "odometry.json"),
    ("dev/la1/cmd", {}, None),
    ("estop", {}, None),
])
def test_a_keys_schema_is_its_shapes_under_the_prefix_or_deeper(tail, body, schema) -> None:
    """``busgate record --prefix fleet`` over gateways under ``fleet/site1`` had no schema
    on any channel: a key's shape was counted from the recording's prefix."""
    assert schema_name(f"busgate/gw1/{tail}", "busgate", body) == schema
    assert schema_name(f"fleet/site1/gw1/{tail}", "fleet", body) == schema
    assert schema_name(f"other/gw1/{tail}", "busgate", body) is None


def test_info_names_each_channel_its_count_and_the_span(recorded) -> None:
    path, _, _ = recorded
    done = run_busgate("record", "--info", str(path))
    assert done.returncode == 0, done
    first, *channels = done.stdout.splitlines()
    assert first.startswith(f"{path}: ") and " messages in " in first and first.endswith(" s")
    assert f"  {COUNT:>8}  {TEST_KEY}  (telemetry.inspire_la)" in channels
    assert f"  {1:>8}  busgate/rec-test/estop  (no schema)" in channels


def test_replay_where_no_gateway_is_live_publishes_telemetry_in_order_never_early_no_command(
        recorded, module_demo, client) -> None:
    """The demo is live under ``busgate``, not under ``replayed``: the replay goes."""
    path, sent, _ = recorded
    done, heard = replayed(client, "replayed/**", path, module_demo, "--prefix", "replayed",
                           "--speed", "2")
    assert done.returncode == 0, done
    first, *_, last = done.stderr.splitlines()
    assert first == f"busgate replay: replaying {path} under replayed/**"
    assert last.endswith(" s; 2 on keys not telemetry (commands, e-stops, frames) left out")
    ours = [(payload, at) for key, payload, at in heard if key == "replayed/rec-test/dev/x/state"]
    assert [payload for payload, _ in ours] == sent
    assert not [key for key, _, _ in heard if key.endswith(("/cmd", "/estop", "/follow"))]
    assert {key.split("/")[1] for key, _, _ in heard} >= {"demo", "rec-test"}
    # paced: the last came no sooner than the recorded span, at twice the speed, after the
    # first (a sleep never wakes early); how close to the pace it keeps, a benchmark's to say
    assert ours[-1][1] - ours[0][1] >= (COUNT - 1) * EVERY_S / 2 * 0.9


def test_replay_publishes_under_replay_by_default(recorded, module_demo, client) -> None:
    path, sent, _ = recorded
    done, heard = replayed(client, "*/rec-test/**", path, module_demo, "--speed", "4")
    assert done.returncode == 0, done
    assert {key.split("/")[0] for key, _, _ in heard} == {"replay"}  # none under busgate
    assert [payload for key, payload, _ in heard if key == "replay/rec-test/dev/x/state"] == sent
    assert done.stderr.splitlines()[0] == f"busgate replay: replaying {path} under replay/**"


def test_replay_under_a_live_gateways_prefix_is_refused_before_it_publishes(
        recorded, module_demo, client) -> None:
    """The demo, a gateway as any other, holds its liveliness token under ``busgate``."""
    path, _, _ = recorded
    done, heard = replayed(client, "*/rec-test/**", path, module_demo, "--prefix", "busgate",
                           "--speed", "4")
    assert done.returncode == 2, done
    assert done.stderr.splitlines() == [live_refusal("busgate", "demo")]
    assert heard == []


def test_replay_onto_live_goes_under_the_live_prefix(recorded, module_demo, client) -> None:
    path, sent, _ = recorded
    done, heard = replayed(client, "*/rec-test/**", path, module_demo, "--prefix", "busgate",
                           "--onto-live", "--speed", "4")
    assert done.returncode == 0, done
    assert done.stderr.splitlines()[0] == f"busgate replay: replaying {path} under busgate/**"
    assert [payload for key, payload, _ in heard if key == TEST_KEY] == sent


def test_replay_leaves_out_a_key_outside_the_recorded_prefix(tmp_path, module_demo,
                                                              client) -> None:
    """A file whose keys are not all under the prefix it names (made so, or recorded from
    key expressions outside it): only those under it are published, under ``--prefix``; and
    none on a wildcard key, one put on which reached every subscriber it covers (an
    audit's)."""
    path = tmp_path / "mixed.mcap"
    with path.open("wb") as stream:
        log = McapLog(stream, "rec")
        log.add("rec/gw9/dev/la1/state", b'{"n": 1}', time.time_ns())
        log.add("busgate/gw9/dev/la1/state", b'{"n": 2}', time.time_ns())
        log.add("rec/*/dev/la1/state", b'{"n": 3}', time.time_ns())
        log.add("rec/**/state", b'{"n": 4}', time.time_ns())
        log.finish()
    done, heard = replayed(client, "*/gw9/**", path, module_demo)
    assert done.returncode == 0, done
    assert [(key, payload) for key, payload, _ in heard] == [
        ("replay/gw9/dev/la1/state", b'{"n": 1}')]
    assert done.stderr.splitlines()[-1].endswith(
        " s; 1 outside rec/**, 2 on wildcard keys left out")


def write_foreign(path) -> None:
    """A complete MCAP file of another tool: its keys under no prefix it names."""
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start()
        channel = writer.register_channel("busgate/gw9/dev/la1/state", "json", 0)
        writer.add_message(channel, log_time=1, data=b"{}", publish_time=1)
        writer.finish()


@pytest.mark.parametrize(("args", "message"), [
    (["record"], "name the file to write"),
    (["record", "-o", "{tmp}/x.mcap", "--seconds", "0"], "--seconds is a positive number"),
    (["record", "-o", "{tmp}/x.mcap", "--seconds", "nan"], "--seconds is a positive number"),
    (["record", "-o", "{tmp}/x.mcap", "a//b"], "a//b"),
    (["record", "-o", "{tmp}/exists.mcap"], "exists: a recording is never overwritten"),
    (["record", "-o", "{tmp}/x.mcap", "busgate/**", "busgate/demo/dev/la1/state"],  # twice each
     "key expressions busgate/** and busgate/demo/dev/la1/state overlap"),
    (["record", "-o", "{tmp}/x.mcap", "a/*/c", "a/b/*"], "a/*/c and a/b/* overlap"),
    (["record", "-o", "{tmp}/no/such/dir/x.mcap"], "cannot write"),
    (["record", "--info", "{tmp}/none.mcap"], "cannot read"),
    (["record", "--info", "{tmp}/exists.mcap"], "is not a complete MCAP file"),
    (["replay", "{tmp}/none.mcap"], "cannot read"),
    (["record", "--info", "{tmp}/fifo.mcap"],  # not waited on
     "busgate record: error: {tmp}/fifo.mcap is no regular file: a recording is one"),
    (["replay", "{tmp}"], "busgate replay: error: {tmp} is no regular file: a recording is one"),
    (["replay", "{tmp}/exists.mcap"], "is not a complete MCAP file"),  # before any session
    (["replay", "{tmp}/exists.mcap", "--prefix", "a*b"], "a*b"),
    (["replay", "{tmp}/exists.mcap", "--speed", "0"], "--speed is from 0.01 to 1000"),
    (["replay", "{tmp}/exists.mcap", "--speed", "1e-300"], "--speed is from 0.01 to 1000"),
    (["replay", "{tmp}/exists.mcap", "--speed", "inf"], "--speed is from 0.01 to 1000"),
    (["replay", "{tmp}/foreign.mcap"], "names no prefix its keys were recorded under"),
    (["record", "--info", "{tmp}/killed.mcap"],  # it said only what mcap's reader did
     "killed.mcap is not a complete MCAP file: it ends short of its summary and index (a "
     "recording killed, or its disk full, before its end): `mcap recover` mends it"),
    (["replay", "{tmp}/huge.mcap"], "huge.mcap holds a chunk of 65 MiB: replay reads at most "
                                   "64 MiB at once"),
])
def test_a_refusal_is_one_line_and_exit_2(tmp_path, args, message, huge_chunk) -> None:
    (tmp_path / "exists.mcap").write_bytes(b"not an mcap file")
    write_foreign(tmp_path / "foreign.mcap")
    with (tmp_path / "killed.mcap").open("wb") as killed:  # chunks written, no summary
        log = mcap_log.McapLog(killed, "busgate")
        for n in range(3000):
            log.add("busgate/gw/dev/la1/state", b'{"position": %d}' % n, n)
    (tmp_path / "huge.mcap").write_bytes(huge_chunk)
    os.mkfifo(tmp_path / "fifo.mcap")
    done = run_busgate(*(a.replace("{tmp}", str(tmp_path)) for a in args),
                       "--connect", "tcp/127.0.0.1:1")
    assert done.returncode == 2, done
    message = message.replace("{tmp}", str(tmp_path))
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "x.mcap").exists(), "a recording that did not start leaves no file"


def test_a_recording_with_no_session_leaves_no_file_and_may_be_run_again(tmp_path) -> None:
    path = tmp_path / "take1.mcap"
    for _ in range(2):  # the second is not refused for a file the first left
        done = run_busgate("record", "-o", str(path), "--seconds", "1",
                           "--connect", "tcp/127.0.0.1:1")
        assert done.returncode == 2 and "cannot open a zenoh session" in done.stderr, done
        assert not path.exists()


def test_seconds_ends_a_recording_with_a_complete_file(module_demo, tmp_path) -> None:
    path = tmp_path / "short.mcap"
    recorder = record(module_demo, path, "--seconds", "1", "busgate/demo/dev/la1/state")
    _, stderr = recorder.communicate(timeout=TIMEOUT_S)
    assert recorder.returncode == 0, stderr
    # stderr no terminal: no progress line redrawn in place, run into the last (an audit)
    assert "\r" not in stderr and stderr.count("busgate record: ") == 2, stderr
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    assert {c.topic for c in summary.channels.values()} == {"busgate/demo/dev/la1/state"}


def test_a_second_ctrl_c_while_the_file_is_finished_leaves_it_complete(module_demo, tmp_path,
                                                                       monkeypatch) -> None:
    """A Ctrl-C pressed twice: the second came while the file got its summary and index, and
    its ``KeyboardInterrupt`` left the file without them. Here it comes from the file's close
    itself, in this process, to land there every time."""
    closing = record_command.Recording.close

    def interrupted_close(recording) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs here, before the close's first line
        closing(recording)

    monkeypatch.setattr(record_command.Recording, "close", interrupted_close)
    path = tmp_path / "twice.mcap"
    assert main(["record", "--connect", module_demo.endpoint, "-o", str(path), "--seconds",
                 "0.5", "busgate/demo/dev/la1/state"]) == 0
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics.message_count > 0


def test_a_recording_stopped_while_its_session_opens_leaves_no_file(tmp_path) -> None:
    """A listener that never speaks zenoh holds the session's opening; SIGTERM then (a
    systemd stop, ``timeout``) ends it in one line, and no file is left for rule 3 to refuse."""
    path = tmp_path / "held.mcap"
    with socket.socket() as mute:
        mute.bind(("127.0.0.1", 0))
        mute.listen()
        endpoint = f"tcp/127.0.0.1:{mute.getsockname()[1]}"
        recorder = subprocess.Popen([*BUSGATE, "record", "-o", str(path), "--connect", endpoint],
                                    stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + TIMEOUT_S
        while not path.exists():  # the file is made first, then the session opens
            assert time.monotonic() < deadline and recorder.poll() is None
            time.sleep(0.05)
        time.sleep(0.5)
        recorder.send_signal(signal.SIGTERM)
        _, stderr = recorder.communicate(timeout=TIMEOUT_S)
    assert recorder.returncode == 2, stderr
    assert stderr.strip().splitlines()[-1].endswith("stopped before a session opened: nothing "
                                                    "recorded"), stderr
    assert not path.exists()


# -- a disk that refuses a write ----------------------------------------------------------------


def test_a_disk_refusing_a_write_ends_the_recording_in_one_line(module_demo, client,
                                                                tmp_path) -> None:
    """A file size limit (``RLIMIT_FSIZE``: the write fails with EFBIG, as a full disk's with
    ENOSPC): the writer's first chunk fails while samples still come, the recording ends by
    itself, the file kept as far as written, the messages it lost counted, and the command
    fails in one line. (Chunks of 1 MiB held the demo's telemetry 15 s before the disk was
    asked, and the messages lost were reported recorded.)"""
    path = tmp_path / "full.mcap"
    # Not measured by coverage (the test command's --cov): the limit would refuse its data
    # file's writes too, and its error would be the last line.
    unmeasured = {k: v for k, v in os.environ.items() if k != "COVERAGE_PROCESS_CONFIG"}
    recorder = subprocess.Popen(["prlimit", "--fsize=4096", *BUSGATE, "record", "--connect",
                                 module_demo.endpoint, "-o", str(path)],
                                stderr=subprocess.PIPE, text=True, env=unmeasured)
    try:
        wait_recording(recorder)
        for _ in range(200):  # 200 kB that zstd cannot shrink: past the first chunk
            client.put("busgate/rec-test/dev/big/state", os.urandom(1000))
        _, stderr = recorder.communicate(timeout=TIMEOUT_S)  # no signal: it ends by itself
    finally:
        recorder.kill()
    assert recorder.returncode == 2, stderr
    lines = stderr.replace("\r", "\n").strip().splitlines()
    assert lines[-1] == f"busgate record: error: cannot write {path}: File too large", stderr
    unwritten = re.fullmatch(r"busgate record: (\d+) messages were not written: the disk "
                             r"refused them", lines[-2])
    assert unwritten is not None and int(unwritten.group(1)) >= 60, stderr  # 64 KiB of them
    assert "Traceback" not in stderr
    assert path.stat().st_size == 4096


class FullDisk(io.RawIOBase):
    """A file on a full disk: every write refused (the writer asks where it is: at 0)."""

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = 0) -> int:
        return 0

    def write(self, data) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_under_a_flood_never_holds_the_recordings_end(monkeypatch) -> None:
    """The writer failed and the queue filled behind it: ``close`` still returns at once."""
    monkeypatch.setattr(record_command, "QUEUE_MAX", 4)
    recording = record_command.Recording(io.BufferedWriter(FullDisk()), "busgate")
    deadline = time.monotonic() + TIMEOUT_S
    while recording.failure is None:  # until the writer's first chunk (1 MiB) is refused
        assert time.monotonic() < deadline
        recording.take("busgate/gw/dev/x/state", os.urandom(64 * 1024), 0)
        time.sleep(0.001)
    for n in range(2000):  # then a flood: the queue fills
        recording.take("busgate/gw/dev/x/state", b"{}", n)
    recording.run_until_stopped(TIMEOUT_S)  # the failed write stopped it, not the seconds
    closing = threading.Thread(target=recording.close, daemon=True)
    closing.start()
    closing.join(TIMEOUT_S)
    assert not closing.is_alive()
    assert recording.failure is not None and recording.failure.errno == errno.ENOSPC


def test_a_chunk_the_disk_refuses_is_counted_though_the_file_buffers_it() -> None:
    """An audit: a compressed chunk (some 6 KB) fit in a buffered file's 8 KiB, was taken for
    written, and the disk's refusal came a chunk later; the messages of the chunk it lost
    were never counted. Flushed with each chunk, the refusal comes with it: every message
    added is in ``unwritten``, or is the one ``add`` raised for."""
    log = mcap_log.McapLog(io.BufferedWriter(FullDisk()), "busgate")
    state = b'{"faults": ["' + b"x" * 1000 + b'"]}'  # a chunk of 60 of them: 2 KB compressed
    added = 0
    with pytest.raises(OSError):
        for n in range(100_000):
            added += 1
            log.add("busgate/gw/dev/la1/state", state, n)
    assert log.unwritten + 1 == added > 1  # as ``Recording`` counts them: all


def test_the_queue_holds_a_bounded_number_of_bytes_whatever_the_messages_sizes(
        monkeypatch) -> None:
    """An audit: a peer's 30 MiB ``joints`` messages, within what a gateway may publish on
    that key, filled a queue of 100,000 messages to gigabytes while the disk wrote a few.
    Past ``QUEUE_MAX_BYTES`` waiting, a message is dropped and counted; once written, its
    room is taken again."""
    monkeypatch.setattr(record_command, "QUEUE_MAX_BYTES", 3 * 1024)
    started, writing = threading.Event(), threading.Event()
    recording = record_command.Recording(io.BytesIO(), "busgate")
    monkeypatch.setattr(recording._log, "add",  # a slow disk
                        lambda *_: started.set() or writing.wait(TIMEOUT_S))
    recording.take("busgate/demo/joints", b"x" * 1024, 0)
    assert started.wait(TIMEOUT_S)  # the writer holds it: three of 1 KiB may wait behind it
    for n in range(1, 10):
        recording.take("busgate/demo/joints", b"x" * 1024, n)
    assert recording.dropped == 6
    writing.set()
    deadline = time.monotonic() + TIMEOUT_S
    while recording._queued_bytes:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    recording.take("busgate/demo/joints", b"x" * 1024, 11)
    assert recording.dropped == 6
    recording.close()


# -- a hostile file -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def huge_chunk() -> bytes:
    """A recording whose one chunk holds 65 MiB of zeros: a few KiB of zstd."""
    stream = io.BytesIO()
    log = McapLog(stream, "rec")
    log.add("rec/gw9/dev/la1/state", bytes(65 * 2**20), 1)
    log.finish()
    return stream.getvalue()


def test_a_chunk_that_holds_more_than_it_claims_is_not_decompressed_past_its_claim(
        huge_chunk) -> None:
    """The chunk and its index made to claim 100 bytes: replay's check before any session
    passes it, and reading stops past those 100 bytes, not at 65 MiB."""
    with io.BytesIO(huge_chunk) as stream:
        claimed = make_reader(stream).get_summary().chunk_indexes[0].uncompressed_size
    size = struct.pack("<Q", claimed)
    assert huge_chunk.count(size) == 2  # the chunk's header and its index
    lying = io.BytesIO(huge_chunk.replace(size, struct.pack("<Q", 100)))
    assert mcap_log.summary(lying)["largest_chunk"] == 100
    with pytest.raises(ValueError, match="not the 100 bytes it names"):
        list(mcap_log.messages(lying))


def test_replay_leaves_out_what_no_gateway_sends_and_cuts_long_gaps(tmp_path, module_demo,
                                                                     client) -> None:
    """A message above the gateway's 64 KiB, keys zenoh refuses (each named once), and
    years between messages: the rest goes, at once at --speed 1000, and the last line
    counts what was left out and cut."""
    path = tmp_path / "hostile.mcap"
    with path.open("wb") as stream:
        log = McapLog(stream, "rec")
        log.add("rec/gw9/dev/la1/state", b'{"n": 1}', 1)
        log.add("rec/gw9/dev/la1/state", b"0" * (64 * 1024 + 1), 2)
        log.add("rec/a#b/dev/la1/state", b'{"n": 0}', 3)
        log.add("rec/a//state", b'{"n": 0}', 4)
        log.add("rec/a//state", b'{"n": 0}', 5)
        log.add("rec/gw9/dev/la1/state", b'{"n": 2}', 10**18)
        log.add("rec/gw9/dev/la1/state", b'{"n": 3}', 2**63)
        log.finish()
    done, heard = replayed(client, "*/gw9/**", path, module_demo, "--speed", "1000")
    assert done.returncode == 0, done
    assert [payload for _, payload, _ in heard] == [b'{"n": 1}', b'{"n": 2}', b'{"n": 3}']
    _, refused1, refused2, last = done.stderr.splitlines()
    assert "'replay/a#b/dev/la1/state'" in refused1 and "'replay/a//state'" in refused2
    assert refused1.startswith("busgate replay: left out: not a key expression: ")
    assert re.match(r"busgate replay: 3 messages in \d+\.\d s; ", last), last
    assert last.endswith(" s; 1 larger than any a gateway sends on its key, 3 on keys zenoh "
                         "refuses left out; 2 gaps "
                         "over 60 s cut to 60 s"), last


def test_ctrl_c_stops_a_replay_between_two_messages(tmp_path, module_demo) -> None:
    path = tmp_path / "slow.mcap"
    with path.open("wb") as stream:
        log = McapLog(stream, "rec")
        for n in range(3):
            log.add("rec/gw9/dev/la1/state", b"{}", n * 50 * 10**9)
        log.finish()
    replay = subprocess.Popen([*BUSGATE, "replay", str(path), "--connect", module_demo.endpoint],
                              stderr=subprocess.PIPE, text=True)
    try:
        assert replay.stderr.readline().startswith("busgate replay: replaying ")
        time.sleep(0.3)
        replay.send_signal(signal.SIGINT)
        _, stderr = replay.communicate(timeout=TIMEOUT_S)
    finally:
        replay.kill()
    assert replay.returncode == 0, stderr
    assert stderr.splitlines() == [stderr.splitlines()[0]]
    # The first message is due at once and the next 50 s later: one went, or none yet on a
    # loaded host, never the rest.
    assert re.fullmatch(r"busgate replay: [01] messages in \d+\.\d s; stopped before the "
                        r"file's end", stderr.rstrip()), stderr


def test_replay_under_a_live_gateways_keys_is_refused(recorded, module_demo, client) -> None:
    path, _, _ = recorded
    done, heard = replayed(client, "busgate/**", path, module_demo, "--prefix", "busgate/demo/x")
    assert done.returncode == 2, done
    assert done.stderr.splitlines() == [live_refusal("busgate/demo/x", "demo under busgate")]
    assert not [key for key, _, _ in heard if key.startswith("busgate/demo/x")]


def test_replay_above_a_live_gateways_prefix_is_refused(recorded, module_demo, client) -> None:
    """A gateway under ``fleet/site1``: a replay under ``fleet`` puts the file's keys where
    that gateway's are (a file recorded under ``fleet`` wrote 30 stale states onto it)."""
    path, _, _ = recorded
    with zenoh.open(session_config(mode="client", connect=[module_demo.endpoint])) as peer:
        info = json.dumps({"ok": True, "gateway": "gw", "version": "9", "buses": []})
        peer.declare_queryable("fleet/site1/gw/info", lambda query: query.reply(
            "fleet/site1/gw/info", info))
        done, heard = replayed(client, "fleet/**", path, module_demo, "--prefix", "fleet")
    assert done.returncode == 2, done
    assert done.stderr.splitlines() == [live_refusal("fleet", "gw under fleet/site1")]
    assert heard == []


def write_keys(path, keys: list[str]) -> McapLog:
    """A recording under ``busgate`` of an empty message on each of ``keys``, in order."""
    with path.open("wb") as stream:
        log = McapLog(stream, "busgate")
        for n, key in enumerate(keys):
            log.add(key, b"{}", n)
        log.finish()
    return log


def test_keys_past_what_a_file_can_name_are_left_out_and_the_file_stays_readable(
        monkeypatch, tmp_path) -> None:
    """A channel's id is 16 bits: the 65,536th key killed the writer (struct.error) and left
    a file no reader could read. Here the most is 3."""
    monkeypatch.setattr(mcap_log, "MAX_CHANNELS", 3)
    path = tmp_path / "keys.mcap"
    keys = [f"busgate/gw{n}/dev/la1/state" for n in range(5)]
    log = write_keys(path, [*keys, keys[0]])  # the last a key it has: taken
    assert log.past_channels == 2
    with path.open("rb") as stream:
        kept = [message.topic for message in mcap_log.messages(stream)]
    assert kept == [f"busgate/gw{n}/dev/la1/state" for n in (0, 1, 2, 0)]


def test_a_sample_larger_than_any_gateway_publishes_is_left_out_and_counted(
        tmp_path, capsys) -> None:
    with (tmp_path / "big.mcap").open("wb") as stream:
        recording = record_command.Recording(stream, "busgate")
        recording.take("busgate/evil/events", b"x" * (64 * 1024 + 1), 1)
        recording.take("busgate/demo/events", b"{}", 2)
        recording.take("busgate/demo/joints", b"x" * (64 * 1024 + 1), 3)  # 400 joints
        recording.take("busgate/evil/joints", b"x" * (MAX_WHOLE_GATEWAY + 1), 4)
        recording.close()
    assert recording.too_large == 2
    err = capsys.readouterr().err
    assert "busgate record: 2 messages left out: larger than any a gateway sends on its key" in err
    with (tmp_path / "big.mcap").open("rb") as stream:
        topics = [m.topic for m in mcap_log.messages(stream)]
    assert topics == ["busgate/demo/events", "busgate/demo/joints"]


@pytest.mark.parametrize("damage", ["length", "name"])
def test_a_file_whose_metadata_is_damaged_is_refused_in_one_line(tmp_path, damage, capsys):
    """A metadata record claiming a terabyte, or a name of four gigabytes, crashed replay
    with a traceback (an audit's); nothing was published, and nothing is."""
    path = tmp_path / "damaged.mcap"
    write_keys(path, ["busgate/gw/dev/la1/state"])
    data = bytearray(path.read_bytes())
    opcode = b"\x0c"  # a Metadata record, its length, then its name
    name = next(i for i in range(len(data)) if data[i:i + 1] == opcode
                and data[i + 9:i + 13 + len(mcap_log.PREFIX_METADATA)]
                == struct.pack("<I", len(mcap_log.PREFIX_METADATA))
                + mcap_log.PREFIX_METADATA.encode()) + 9
    at = name - 8 if damage == "length" else name  # the record's length, or its name's
    data[at:at + (8 if damage == "length" else 4)] = (
        struct.pack("<Q", 2**40) if damage == "length" else struct.pack("<I", 0xFFFFFFFF))
    path.write_bytes(bytes(data))
    assert main(["replay", str(path), "--connect", "tcp/127.0.0.1:1"]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"busgate replay: error: {path}: its metadata cannot be read ("), line


def test_a_file_whose_keys_take_too_much_is_refused_as_it_is_read(tmp_path, monkeypatch):
    """Thousands of channels of a megabyte's key each, from a small compressed file, held
    1.6 GB while replay or --timeline read it (an audit's): the keys held are bounded."""
    monkeypatch.setattr(mcap_log, "MAX_TOPIC_BYTES", 100)
    path = tmp_path / "keys.mcap"
    write_keys(path, [f"busgate/gw/dev/{'d' * 30}{n}/state" for n in range(4)])
    with path.open("rb") as stream, pytest.raises(ValueError, match="channels whose keys take"):
        list(mcap_log.messages(stream))
