"""What ``busgate sim`` refuses, and how: one line naming the option, exit status 2, no
traceback, and nothing made, truncated or replaced on the way (gateway/sim/cli.py, rules 1–3).
Refusals run the CLI in this process, with serving made to fail so that a command that should
have been refused fails the test instead of serving forever; the one run that must serve is a
child process."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from busgate.gateway.cli import build_parser, main
from busgate.gateway.sim import cli as sim_cli
from busgate.gateway.sim.process import SimProcess

OLD_RECORD = "frames of an earlier run\n"


@pytest.fixture(autouse=True)
def never_serve(monkeypatch) -> None:
    def serving(*_: object) -> None:
        raise AssertionError("busgate sim started serving instead of refusing")

    monkeypatch.setattr(sim_cli, "_install_signals", serving)


def refusal(capsys, *args: str) -> str:
    """Run ``busgate sim ARGS``, expect status 2, and return the error line it printed last."""
    try:
        status = main(["sim", *args])
    except SystemExit as exited:  # refused by the parser
        status = exited.code
    assert status == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.splitlines()[-1]


def listing(folder: Path) -> dict[str, str]:
    """Each name in ``folder`` and what it is: a file's text, a symlink's target, or a dir."""
    return {path.name: _what(path) for path in folder.iterdir()}


def _what(path: Path) -> str:
    if path.is_symlink():
        return "-> " + os.readlink(path)
    return "dir" if path.is_dir() else path.read_text()


# -- --record ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad", [["--ids", "0"], ["--drop-rate", "5"], ["--stroke-s", "0"], ["--fault", "9:stall"]]
)
def test_a_refused_command_leaves_an_existing_record_as_it_was(bad, tmp_path, capsys) -> None:
    record = tmp_path / "k1.txt"
    record.write_text(OLD_RECORD)
    refusal(capsys, "inspire_la", "--record", str(record), *bad)
    assert record.read_text() == OLD_RECORD


def test_a_refused_command_creates_no_record(tmp_path, capsys) -> None:
    refusal(capsys, "inspire_la", "--record", str(tmp_path / "new.jsonl"), "--ids", "0")
    assert listing(tmp_path) == {}


def test_an_existing_record_is_written_again_once_everything_is_taken(tmp_path) -> None:
    """A record is a run's (the benchmarks write theirs again each step): overwritten, but
    only once nothing is refused (here: right before it would serve)."""
    record = tmp_path / "k1.txt"
    record.write_text(OLD_RECORD)
    with pytest.raises(AssertionError, match="started serving"):
        main(["sim", "inspire_la", "--record", str(record)])
    assert record.read_text() == ""


def test_a_record_that_is_a_directory_is_refused(tmp_path, capsys) -> None:
    (tmp_path / "adir").mkdir()
    line = refusal(capsys, "inspire_la", "--record", str(tmp_path / "adir"))
    assert line == f"busgate sim: error: cannot write --record {tmp_path / 'adir'}: Is a directory"


def test_a_link_to_someone_elses_file_or_adapter_is_kept(tmp_path, capsys) -> None:
    """A symlink is replaced only when a simulator made it (to a pty, or dangling): a udev
    link to a real adapter (/dev/serial/by-id/...) or to a file is not the simulator's."""
    (tmp_path / "notes").write_text("mine\n")
    (tmp_path / "by-id-link").symlink_to(tmp_path / "notes")
    line = refusal(capsys, "inspire_la", "--link", str(tmp_path / "by-id-link"))
    assert line.endswith("by-id-link: exists and is not a simulator's link to a pty, so it is "
                         "kept")
    assert os.readlink(tmp_path / "by-id-link") == str(tmp_path / "notes")


def test_a_record_in_a_missing_folder_is_refused_in_one_line(tmp_path, capsys) -> None:
    record = tmp_path / "nowhere" / "wire.jsonl"
    line = refusal(capsys, "inspire_la", "--record", str(record))
    assert line == f"busgate sim: error: cannot write --record {record}: No such file or directory"


# -- --link -----------------------------------------------------------------------------------


def test_a_file_at_the_link_is_kept_and_the_command_refused(tmp_path, capsys) -> None:
    kept = tmp_path / "k2.txt"
    kept.write_text("someone's notes\n")
    record = tmp_path / "wire.jsonl"
    record.write_text(OLD_RECORD)
    line = refusal(capsys, "inspire_la", "--link", str(kept), "--record", str(record))
    assert line == (f"busgate sim: error: --link {kept}: exists and is not a simulator's link "
                    "to a pty, so it is kept")
    assert listing(tmp_path) == {"k2.txt": "someone's notes\n", "wire.jsonl": OLD_RECORD}


def test_a_directory_at_the_link_is_refused_leaving_nothing_behind(tmp_path, capsys) -> None:
    (tmp_path / "adir").mkdir()
    line = refusal(capsys, "inspire_la", "--link", str(tmp_path / "adir"))
    assert line.endswith("adir: exists and is not a simulator's link to a pty, so it is kept")
    assert listing(tmp_path) == {"adir": "dir"}
    assert listing(tmp_path / "adir") == {}


def test_a_link_in_a_missing_folder_is_refused_leaving_nothing_behind(tmp_path, capsys) -> None:
    link = tmp_path / "nonexistent" / "x"
    record = tmp_path / "wire.jsonl"
    line = refusal(capsys, "zlac706_can", "--link", str(link), "--record", str(record))
    assert line == f"busgate sim: error: --link {link}: No such file or directory"
    assert listing(tmp_path) == {}


def test_a_symlink_an_earlier_simulator_left_is_replaced_then_removed(tmp_path) -> None:
    link, record = tmp_path / "usb-la", tmp_path / "wire.jsonl"
    link.symlink_to("/dev/pts/gone")
    simulator = SimProcess("inspire_la", ["--link", str(link), "--record", str(record)])
    try:
        assert simulator.port == str(link)
        assert os.readlink(link).startswith("/dev/pts/") and link.exists()
    finally:
        assert simulator.stop() == 0
    assert listing(tmp_path) == {"wire.jsonl": ""}


# -- numbers ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("protocol", "option", "value", "allowed"),
    [
        ("inspire_la", "--stroke-s", "0", "seconds, 0.001 to 86400"),
        ("inspire_la", "--stroke-s", "-1", "seconds, 0.001 to 86400"),
        ("inspire_la", "--stroke-s", "nan", "seconds, 0.001 to 86400"),
        ("inspire_la", "--stroke-s", "inf", "seconds, 0.001 to 86400"),
        ("zlac706_can", "--heartbeat-ms", "-1", "a whole number of ms, 0 (none) to 86400000"),
        ("zlac706_can", "--bitrate", "0", "a whole number of bit/s, 1 to 1000000"),
        ("zlac706_can", "--bitrate", "-1", "a whole number of bit/s, 1 to 1000000"),
        ("zlac706_can", "--bitrate", "2000000", "a whole number of bit/s, 1 to 1000000"),
        ("ds_servo", "--baudrate", "0", "a whole number of baud above 0"),
        ("ds_servo", "--baudrate", "-9600", "a whole number of baud above 0"),
        ("ds_servo", "--baudrate", "fast", "a whole number of baud above 0"),
        ("inspire_la", "--busy-poll-ms", "-1", "ms, 0 to 86400000"),
        ("inspire_la", "--busy-poll-ms", "1e309", "ms, 0 to 86400000"),
        ("inspire_la", "--late-ms", "nan", "ms, 0 to 86400000"),
        ("inspire_la", "--late-ms", "1e300", "ms, 0 to 86400000"),
        ("inspire_la", "--drop-rate", "5", "a share, 0 to 1"),
        ("inspire_la", "--garbage-rate", "-0.1", "a share, 0 to 1"),
        ("inspire_la", "--late-rate", "nan", "a share, 0 to 1"),
        ("inspire_la", "--bad-checksum-rate", "1.5", "a share, 0 to 1"),
    ],
)
def test_a_number_out_of_range_is_refused_naming_the_option(
    protocol, option, value, allowed, capsys
) -> None:
    with pytest.raises(SystemExit) as exited:
        build_parser("sim").parse_args(["sim", protocol, option, value])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"busgate sim: error: argument {option}: must be {allowed}, not {value!r}"
    )


def test_an_id_given_twice_is_refused(capsys) -> None:
    """Two simulated devices of one id both answered every frame to it."""
    assert refusal(capsys, "inspire_la", "--ids", "1,2,1") == (
        "busgate sim: error: id 1 is given twice: one device an id")


@pytest.mark.parametrize(
    "arguments",
    [  # as the docs, the tests and the benchmarks give them
        ["inspire_la", "--ids", "1,3", "--baudrate", "115200", "--stroke-s", "2"],
        ["ds_servo", "--baudrate", "1000000", "--busy-poll-ms", "0.0"],
        ["zlac706_can", "--ids", "1", "--heartbeat-ms", "0", "--bitrate", "500000"],
        ["zlac706_can", "--heartbeat-ms", "100", "--bitrate", "1000000"],
        [
            "ds_servo",
            "--drop-rate",
            "0.1",
            "--garbage-rate",
            "0.1",
            "--late-rate",
            "1",
            "--late-ms",
            "0",
            "--bad-checksum-rate",
            "0",
            "--busy-poll-ms",
            "50",
        ],
    ],
)
def test_the_numbers_in_use_are_accepted(arguments) -> None:
    build_parser("sim").parse_args(["sim", *arguments])
