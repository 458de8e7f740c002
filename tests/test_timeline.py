"""``busgate record --timeline``: an incident file's frames drawn as SVG, a lane a bus.

A file written here by the recorder's own writer (``McapLog``, the shape an incident file's
frames have) is drawn: each frame in the window is one mark on its bus's lane, sent above and
received below, the e-stop a line across, the figures beside each lane the host's (the least
time from a frame received to the next sent, the median between two sent). A file's frame
messages of any other shape are left out and counted, a bus name is text, never markup, and a
window with more frames than a picture draws is refused. A real incident file, from the
demo, is drawn in ``tests/test_incidents.py``."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from busgate.gateway.cli import main
from busgate.gateway.recording import timeline
from busgate.gateway.recording.mcap_log import McapLog

SVG = "{http://www.w3.org/2000/svg}"
T0 = 1_800_000_000.0


def frame(ts: float, bus: str, direction: str, wire: str = "55aa0301") -> tuple[str, dict]:
    return f"busgate/gw/bus/{bus}/frames", {"ts": ts, "bus": bus, "dir": direction, "wire": wire}


def write_incident(path: Path, messages: list[tuple[str, object]]) -> None:
    """``messages`` (key, body: a dict as JSON, bytes as they are) at their ``ts`` (or in a
    row, a millisecond apart, where they have none)."""
    with path.open("wb") as stream:
        log = McapLog(stream, "busgate")
        for n, (key, body) in enumerate(messages):
            data = body if isinstance(body, bytes) else json.dumps(body).encode()
            ts = body.get("ts") if isinstance(body, dict) else None
            ts = ts if isinstance(ts, float) else T0 + n * 1e-3
            log.add(key, data, int(ts * 1e9))
        log.finish()


def lanes(picture: str) -> dict[str, ET.Element]:
    root = ET.fromstring(picture)
    return {lane.get("data-bus"): lane for lane in root.iter(f"{SVG}g")}


def marks(lane: ET.Element, kind: str) -> list[ET.Element]:
    return [rect for rect in lane.iter(f"{SVG}rect") if rect.get("class") == kind]


@pytest.fixture
def incident(tmp_path: Path) -> Path:
    """uart0: a poll every 10 ms (sent, then its reply 0.3 ms later) from T0, the least gap
    1.2 ms; can0: one frame each way every 20 ms; an e-stop received at T0 + 50 ms."""
    messages = []
    for n in range(10):
        messages += [frame(T0 + n * 0.010, "uart0", "tx"),
                     frame(T0 + n * 0.010 + 0.0003, "uart0", "rx")]
    messages.append(frame(T0 + 0.0915, "uart0", "tx"))  # 1.2 ms after the last reply
    messages += [frame(T0 + n * 0.020, "can0", d, "601#2b") for n in range(5) for d in ("tx", "rx")]
    messages.append(("busgate/gw/events", {"type": "estop", "ts": T0 + 0.051}))  # not a mark
    messages.append(("busgate/gw/commands", {"ts": T0 + 0.050, "key": "busgate/*/estop",
                                             "command": {}, "client": "op", "code": "ok"}))
    messages.sort(key=lambda message: message[1]["ts"])
    path = tmp_path / "incident.mcap"
    write_incident(path, messages)
    return path


def test_each_frame_in_the_window_is_a_mark_on_its_lane_the_estop_a_line(incident) -> None:
    with incident.open("rb") as stream:
        window = timeline.window_of(stream, 0.060)  # ends a fifth of it after the e-stop
    assert window.end == pytest.approx(T0 + 0.062) and window.estops == [pytest.approx(T0 + 0.05)]
    picture = timeline.svg(window)
    drawn = lanes(picture)
    assert set(drawn) == {"uart0", "can0"}
    assert len(marks(drawn["uart0"], "tx")) == 6 and len(marks(drawn["uart0"], "rx")) == 6
    assert len(marks(drawn["can0"], "tx")) == 3  # T0 + 20, 40, 60 ms (the window from T0 + 2)
    [estop] = [line for line in ET.fromstring(picture).iter(f"{SVG}line")
               if line.get("class") == "estop"]
    x = float(estop.get("x1"))
    left, right = timeline.LEFT, timeline.WIDTH - timeline.RIGHT
    assert x == pytest.approx(left + (right - left) * 48 / 60)  # 48 ms into 60
    assert "received → sent ≥ 9.70 ms" in picture and "sent every 10.00 ms (median)" in picture


def test_the_figures_are_the_least_gap_received_to_sent_and_the_median_period() -> None:
    frames = [timeline.WireFrame(t, sent, "") for t, sent in
              [(0.0, True), (0.0004, False), (0.0016, True), (0.0019, False), (0.0200, True)]]
    assert timeline.smallest_gap_s(frames) == pytest.approx(0.0012)
    assert timeline.median_period_s(frames) == pytest.approx(0.0100)  # steps 1.6, 18.4 ms
    assert timeline.smallest_gap_s(frames[:1]) is None and timeline.median_period_s([]) is None


def test_the_command_writes_the_picture_and_never_over_a_file(incident, tmp_path, capsys):
    out = tmp_path / "t.svg"
    argv = ["record", "--timeline", str(incident), "--span-ms", "100", "--end", str(T0 + 0.095),
            "-o", str(out)]
    assert main(argv) == 0
    assert len(marks(lanes(out.read_text())["uart0"], "tx")) == 11
    assert "busgate record: 31 frames on can0, uart0 drawn, 100 ms" in capsys.readouterr().err
    assert main(argv) == 2
    assert f"{out} exists: give a new file name" in capsys.readouterr().err
    assert main(["record", "--timeline", str(incident), "--end", str(T0 + 10)]) == 2
    assert "holds no frames in those 100 ms" in capsys.readouterr().err


@pytest.mark.parametrize(("args", "words"), [
    (["--span-ms", "0"], "--span-ms is from 1 to 60000, not 0.0"),
    (["--span-ms", "nan"], "--span-ms is from 1 to 60000, not nan"),
    (["--end=-inf"], "--end is a Unix time in seconds, not -inf"),
    (["--end", "0"], "--end is a Unix time in seconds, not 0.0"),
])
def test_a_bad_window_is_refused_in_one_line(incident, capsys, args, words) -> None:
    assert main(["record", "--timeline", str(incident), *args]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"busgate record: error: {words}"]


def test_a_files_word_is_drawn_as_text_and_what_is_not_a_frame_left_out(tmp_path) -> None:
    hostile = "<script>alert(1)</script>"
    path = tmp_path / "hostile.mcap"
    write_incident(path, [
        frame(T0, hostile, "tx", "</title><script>x</script>"),
        ("busgate/gw/bus/a/frames", b"not json"),
        ("busgate/gw/bus/a/frames", b"[1, 2]"),
        ("busgate/gw/bus/a/frames", {"ts": T0, "bus": "a", "dir": "up", "wire": "00"}),
        ("busgate/gw/bus/a/frames", {"ts": "soon", "bus": "a", "dir": "tx", "wire": "00"}),
        ("busgate/gw/bus/a/frames", {"ts": T0, "bus": 7, "dir": "tx", "wire": "00"}),
        ("busgate/gw/commands", b"\xff"),
        ("busgate/gw/commands", b"[]"),
    ])
    with path.open("rb") as stream:
        window = timeline.window_of(stream, 1.0, T0 + 0.5)
    assert window.left_out == 5 and list(window.frames) == [hostile]
    picture = timeline.svg(window)
    assert "<script>" not in picture
    assert list(lanes(picture)) == [hostile]  # the name, as text


def test_more_frames_than_a_picture_draws_are_refused(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(timeline, "MAX_FRAMES", 3)
    path = tmp_path / "many.mcap"
    write_incident(path, [frame(T0 + n * 1e-3, "u", "tx") for n in range(4)])
    with path.open("rb") as stream, pytest.raises(ValueError, match="more than 3 frames in 10 ms"):
        timeline.window_of(stream, 0.010)


def test_a_file_that_is_no_recording_is_refused_saying_why(tmp_path, capsys) -> None:
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert main(["record", "--timeline", str(empty)]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"busgate record: error: {empty} is not a complete MCAP file: ")
    assert not line.endswith(":"), "the reader's error said nothing: its kind is said"


def test_what_xml_cannot_hold_is_drawn_as_a_replacement_and_the_file_is_written(
        tmp_path, capsys) -> None:
    """A lone surrogate in a bus's name crashed the command, leaving an empty file behind,
    and a control character made a picture no viewer reads; a frame nested past what the
    JSON reader takes refused the whole file, and a bus's name printed its escapes to the
    terminal (an audit's). Each is drawn, left out, or shown escaped."""
    path = tmp_path / "odd.mcap"
    deep = b'{"ts": 1, "bus": "x", "dir": "tx", "wire": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    write_incident(path, [
        ("busgate/gw/bus/u/frames", {"ts": T0, "bus": "uart\ud800", "dir": "tx",
                                     "wire": "00\x01\x0b"}),
        ("busgate/gw/bus/c/frames", {"ts": T0 + 1e-3, "bus": "can\x1b[2J", "dir": "rx",
                                     "wire": "00"}),
        ("busgate/gw/bus/a/frames", deep),
        ("busgate/gw/commands", b'{"key": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"),
    ])
    out = tmp_path / "odd.svg"
    assert main(["record", "--timeline", str(path), "--end", str(T0 + 0.01),
                 "-o", str(out)]) == 0
    picture = out.read_text(encoding="utf-8")
    assert set(lanes(picture)) == {"uart\ufffd", "can\ufffd[2J"}  # parsed: well-formed
    said = capsys.readouterr().err
    assert "\x1b" not in said and "1 frame messages not a recorder's, left out" in said, said


def test_a_flood_of_estops_marks_at_most_max_marks(tmp_path) -> None:
    """A small file of a million e-stops made a picture of 147 MB (an audit's)."""
    estop = ("busgate/gw/commands", {"ts": T0, "key": "busgate/*/estop", "command": {}})
    path = tmp_path / "estops.mcap"
    write_incident(path, [frame(T0, "u", "tx")] + [
        ("busgate/gw/commands", {**estop[1], "ts": T0 + n * 1e-6}) for n in range(300)])
    with path.open("rb") as stream:
        window = timeline.window_of(stream, 0.010)
    assert len(window.estops) == timeline.MAX_MARKS
    assert window.estops == sorted(window.estops)


@pytest.mark.parametrize(("args", "words"), [
    (["-o", "x.mcap", "--span-ms", "200"],
     "--span-ms cannot go with a recording (no --info, no --timeline)"),
    (["-o", "x.mcap", "--end", "5"], "--end cannot go with a recording (no --info, no --timeline)"),
    (["--info", "x.mcap", "--timeline", "x.mcap", "-o", "y.svg"],
     "--timeline and -o cannot go with --info"),
    (["--timeline", "x.mcap", "--seconds", "3", "busgate/**"],
     "--seconds and a KEYEXPR cannot go with --timeline"),
])
def test_an_option_its_mode_would_ignore_is_refused(tmp_path, monkeypatch, capsys, args, words):
    monkeypatch.chdir(tmp_path)
    assert main(["record", *args]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"busgate record: error: {words}"]
    assert list(tmp_path.iterdir()) == []  # nothing written, no session opened
