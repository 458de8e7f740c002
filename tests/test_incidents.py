"""The flight recorder in a running gateway: ``busgate demo --incidents DIR`` (the daemon's
``serve`` with ``[recorder]``) as a child process, its simulators recording their wire.

An e-stop writes an incident file whose frames are the very bytes the devices saw, in order,
up to the e-stop and past it (its stop frames); the commands are there with their client and
reply code, the telemetry with its schemas. SIGUSR1 asks for one, and one still pending at
SIGTERM is written after the devices' safe state. ``busgate record --timeline`` draws a
file's frames around its e-stop. Without a recorder SIGUSR1 ends nothing.
A recorder folder that cannot be written refuses the start in one line."""

from __future__ import annotations

import json
import math
import signal
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from mcap.reader import make_reader

import busgate.client as bc
from tests.conftest import unused_loopback_port
from tests.gateway_process import DemoProcess, run_busgate, serial_bus, write_config

FOLLOW_S = 1.0
SVG = "{http://www.w3.org/2000/svg}"


def incidents(folder: Path) -> list[Path]:
    return sorted(folder.glob("incident-*.mcap"))


def wait_incidents(folder: Path, count: int, timeout: float = 20.0) -> list[Path]:
    deadline = time.monotonic() + timeout
    while len(found := incidents(folder)) < count:
        assert time.monotonic() < deadline, f"{len(found)} incident files, not {count}"
        time.sleep(0.1)
    return found


def read(path: Path) -> tuple[list[tuple[str, str | None, int, dict]], dict[str, str]]:
    """Every message (topic, schema name, log time ns, body) and the incident metadata."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        messages = [(channel.topic, schema.name if schema else None, message.log_time,
                     json.loads(message.data))
                    for schema, channel, message in reader.iter_messages(log_time_order=True)]
        [metadata] = [dict(m.metadata) for m in reader.iter_metadata() if m.name == "incident"]
    return messages, metadata


def wire_record(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def estopped(tmp_path_factory):
    """A demo that streamed to la1, was e-stopped, then got SIGUSR1 and at once SIGTERM: its
    incident folder, its simulators' wire records, and when the e-stop was sent."""
    root = tmp_path_factory.mktemp("incidents")
    folder, wires = root / "incidents", root / "wire"
    demo = DemoProcess(f"tcp/127.0.0.1:{unused_loopback_port()}", "--no-dashboard", "--incidents",
                       str(folder), "--record", str(wires))
    try:
        with bc.connect(demo.endpoint, client_id="incident-test") as client:
            la1 = client.device("la1")
            with la1.claim(ttl_s=5.0), la1.follow() as stream:
                start = time.monotonic()
                while (t := time.monotonic() - start) < FOLLOW_S:
                    stream.set(position=round(1000 + 400 * math.sin(2 * math.pi * t)))
                    time.sleep(0.02)
            estop_at = time.time()
            client.estop()
            first = wait_incidents(folder, 1)
        demo.process.send_signal(signal.SIGUSR1)
        time.sleep(0.3)  # taken, but within AFTER_S: pending when the stop comes
        assert demo.terminate() == 0
    finally:
        demo.terminate()
    return {"folder": folder, "wires": wires, "first": first[0], "estop_at": estop_at}


def test_an_estop_writes_an_incident_naming_it(estopped) -> None:
    assert estopped["first"].name.startswith("incident-demo-")
    assert estopped["first"].name.endswith("-estop.mcap")
    _, metadata = read(estopped["first"])
    assert metadata["triggers"] == "e-stop from incident-test"
    assert metadata["gateway"] == "demo" and float(metadata["seconds"]) == 60


def test_its_frames_are_the_bytes_the_devices_saw_up_to_the_estop_and_past_it(estopped):
    messages, _ = read(estopped["first"])
    [estop_ns] = [t for topic, _, t, body in messages
                  if topic == "busgate/demo/events" and body["type"] == "estop"]
    for bus in ("uart0", "uart1", "rs232"):
        frames = [(t, body) for topic, schema, t, body in messages
                  if topic == f"busgate/demo/bus/{bus}/frames"]
        assert {schema for topic, schema, _, _ in messages
                if topic == f"busgate/demo/bus/{bus}/frames"} == {"frame"}
        sent = [body["wire"] for _, body in frames if body["dir"] == "tx"]
        device_side = wire_record(estopped["wires"] / f"{bus}.jsonl")
        seen = [r["wire"] for r in device_side if r["dir"] == "rx"]
        assert sent == seen[: len(sent)], bus  # every frame, in order, none more
        read_in = "".join(body["wire"] for _, body in frames if body["dir"] == "rx")
        answered = "".join(r["wire"] for r in device_side if r["dir"] == "tx")
        assert answered.startswith(read_in), bus  # every byte read is a byte the devices sent
        assert sum(t < estop_ns for t, _ in frames) > 10 and any(t > estop_ns for t, _ in frames)
    streamed = [body for topic, _, t, body in messages
                if topic == "busgate/demo/bus/uart0/frames" and body["dir"] == "tx"
                and t < estop_ns]
    assert len(streamed) >= FOLLOW_S * 1000 / 20 / 2  # la1's follow ticks, 20 ms apart
    can = [body["wire"] for topic, _, _, body in messages
           if topic == "busgate/demo/bus/can0/frames" and body["dir"] == "tx"]
    seen = [r["wire"] for r in wire_record(estopped["wires"] / "can0.jsonl") if r["dir"] == "rx"]
    assert can and can == seen[: len(can)]


def test_its_commands_carry_their_client_and_code_and_its_telemetry_its_schema(estopped):
    messages, _ = read(estopped["first"])
    commands = [body for topic, schema, _, body in messages
                if topic == "busgate/demo/commands" and schema == "recorded_command"]
    ops = [(c["key"].rsplit("/", 1)[-1], (c["command"] or {}).get("op"), c["code"])
           for c in commands]
    assert ("cmd", "claim", "ok") in ops and ("cmd", "end_follow", "ok") in ops
    follows = [c for c in commands if c["key"] == "busgate/demo/dev/la1/follow"]
    assert len(follows) > 10 and {c["client"] for c in follows} == {"incident-test"}
    assert {c["code"] for c in follows} == {"ok"}
    assert commands[-1]["key"] == "busgate/*/estop" and commands[-1]["code"] == "ok"  # all
    assert commands[-1]["client"] == "incident-test"
    schemas = {topic: schema for topic, schema, _, _ in messages}
    assert schemas["busgate/demo/dev/la1/state"] == "telemetry.inspire_la"
    assert schemas["busgate/demo/dev/wheel/state"] == "telemetry.zlac706"
    assert schemas["busgate/demo/events"] == "event"
    times = [t for _, _, t, _ in messages]
    assert times == sorted(times)


def test_sigusr1_pending_at_the_stop_is_written_after_the_safe_state(estopped) -> None:
    files = incidents(estopped["folder"])
    assert len(files) == 2 and files[1].name.endswith("-signal.mcap")
    assert not list(estopped["folder"].glob("*.part"))
    messages, metadata = read(files[1])
    assert metadata["triggers"] == "SIGUSR1 from an operator"
    sent = [body["wire"] for topic, _, _, body in messages
            if topic == "busgate/demo/bus/uart0/frames" and body["dir"] == "tx"]
    seen = [r["wire"] for r in wire_record(estopped["wires"] / "uart0.jsonl") if r["dir"] == "rx"]
    assert sent == seen  # to the last frame the devices got, their safe state on the way out


def test_without_a_recorder_sigusr1_ends_nothing(tmp_path, free_port) -> None:
    with (tmp_path / "demo.log").open("w+") as log:
        demo = DemoProcess(f"tcp/127.0.0.1:{free_port()}", "--no-dashboard", stderr=log)
        try:
            demo.process.send_signal(signal.SIGUSR1)
            with bc.connect(demo.endpoint, client_id="incident-test-2") as client:
                assert client.device("la1").state() is not None
            assert demo.process.poll() is None
        finally:
            assert demo.terminate() == 0
        log.seek(0)
        assert "SIGUSR1: no flight recorder" in log.read()


def test_a_folder_that_cannot_be_written_refuses_the_start(tmp_path, free_port) -> None:
    (tmp_path / "a-file").write_text("")
    config = write_config(tmp_path / "gw.toml", f"tcp/127.0.0.1:{free_port()}",
                          serial_bus("b", "/dev/busgate-no-such-port", "la1"))
    config.write_text(config.read_text().replace(
        "[[buses]]", f'[recorder]\ndir = "{tmp_path}/a-file/incidents"\n[[buses]]', 1))
    result = run_busgate("run", "--config", str(config))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.splitlines()[-1] == (
        f"busgate run: error: recorder: {tmp_path}/a-file is a file, not a folder (the "
        "[recorder] dir of the config)")
    assert "zenoh session up" not in result.stderr  # refused before anything opened


def test_its_wire_is_drawn_bus_by_bus_around_the_estop(estopped, tmp_path) -> None:
    picture = tmp_path / "estop.svg"
    done = run_busgate("record", "--timeline", str(estopped["first"]), "--span-ms", "200",
                       "-o", str(picture))
    assert done.returncode == 0, done.stderr
    messages, _ = read(estopped["first"])
    [estop_ns] = [t for topic, _, t, body in messages  # when the e-stop came
                  if topic == "busgate/demo/commands" and body["key"] == "busgate/*/estop"]
    end_ns, start_ns = estop_ns + 40e6, estop_ns - 160e6  # a fifth of 200 ms after it
    root = ET.fromstring(picture.read_text())
    drawn = {lane.get("data-bus"): lane for lane in root.iter(f"{SVG}g")}
    assert {"uart0", "uart1", "rs232", "can0"} <= set(drawn)
    for bus, lane in drawn.items():
        sent = [t for topic, _, t, body in messages if topic == f"busgate/demo/bus/{bus}/frames"
                and body["dir"] == "tx" and start_ns <= t <= end_ns]
        assert len([r for r in lane.iter(f"{SVG}rect") if r.get("class") == "tx"]) == len(sent)
    assert len([line for line in root.iter(f"{SVG}line") if line.get("class") == "estop"]) == 1
    stops = [t for topic, _, t, body in messages if topic == "busgate/demo/bus/uart0/frames"
             and body["dir"] == "tx" and body["wire"][8:14] == "040023"]  # an LA's e-stop
    assert stops and min(stops) >= estop_ns, "the e-stop is dated when it came, before its frames"
