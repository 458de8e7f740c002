"""Every command's file and folder arguments refuse an empty path: ``Path("")`` is the working
directory, where ``demo --record ''`` wrote its simulators' records and ``schema --out ''``
its schemas, and where an empty ``--zenoh-config`` was read as none."""

from __future__ import annotations

import pytest

from busgate.gateway.cli import main
from busgate.schemas.files import EMPTY_PATH


@pytest.mark.parametrize(("args", "named"), [
    (["check-config", ""], "file"),
    (["demo", "--record", ""], "--record"),
    (["demo", "--incidents", ""], "--incidents"),
    (["schema", "--out", ""], "--out"),
    (["record", "-o", ""], "-o/--output"),
    (["record", "--info", ""], "--info"),
    (["record", "--timeline", ""], "--timeline"),
    (["replay", ""], "FILE.mcap"),
    (["router", "--listen", "tcp/127.0.0.1:1", "--config", ""], "--config"),
    (["send", "--zenoh-config", "", "la1", "{}"], "--zenoh-config"),
    (["watch", "--password-file", "", "--user", "u"], "--password-file"),
    (["dashboard", "--ca", ""], "--ca"),
])
def test_an_empty_path_is_refused_before_anything_runs(args, named, tmp_path, monkeypatch,
                                                        capsys) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exited:
        main(args)
    assert exited.value.code == 2
    assert capsys.readouterr().err.endswith(
        f"argument {named}: {EMPTY_PATH}\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("args", "said"), [
    # commands of rooms below the command line's: refused as they read or open the path
    (["run", "--config", ""], "busgate run: error: "),
    (["sim", "inspire_la", "--record", ""], "busgate sim: error: --record: "),
])
def test_an_empty_path_is_refused_by_the_command_that_reads_it(args, said, tmp_path,
                                                               monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    assert capsys.readouterr().err.endswith(f"{said}{EMPTY_PATH}\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("under", ["", "/records"])
@pytest.mark.parametrize(("args", "said"), [
    (["demo", "--listen", "tcp/127.0.0.1:1", "--no-dashboard", "--record"],
     "cannot write wire records: "),
    (["schema", "--out"], "--out: "),
])
def test_a_file_named_as_a_folder_is_refused_as_one(args, said, under, tmp_path,
                                                    capsys) -> None:
    """Not in mkdir's words ("File exists", "Not a directory"): the file in the way is named,
    whether it is the folder itself or one of its parents."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main([*args, f"{blocker}{under}"]) == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(
        f"error: {said}{blocker} is a file, not a folder")
    assert blocker.read_text() == ""
