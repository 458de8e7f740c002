"""The gateway's log lines under systemd's journal carry their priority (``service.logs``):
journald took every line for info, and ``journalctl -p warning`` showed none."""

from __future__ import annotations

import os
import subprocess
import sys

LOG_TWO = (
    "from busgate.gateway.service import logs; import logging; logs.configure('INFO'); "
    "logging.getLogger('busgate').warning('held\\nback'); logging.getLogger('busgate').info('up')"
)


def _stderr_of(tmp_path, env: dict[str, str]) -> str:
    path = tmp_path / "stderr"
    with path.open("w") as stderr:
        found = os.fstat(stderr.fileno())
        journal = {"JOURNAL_STREAM": f"{found.st_dev}:{found.st_ino}"} if env is None else env
        ours = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
        subprocess.run([sys.executable, "-c", LOG_TWO], stderr=stderr, check=True,
                       env={**ours, **journal})
    return path.read_text()


def test_each_line_starts_with_its_priority_when_stderr_is_the_journals_stream(tmp_path):
    assert _stderr_of(tmp_path, None).splitlines() == [
        "<4>WARNING busgate: held", "<4>back", "<6>INFO busgate: up"]


def test_on_another_stream_the_lines_are_as_ever(tmp_path):
    plain = ["WARNING busgate: held", "back", "INFO busgate: up"]
    assert _stderr_of(tmp_path, {}).splitlines() == plain
    other = {"JOURNAL_STREAM": "1:2"}  # a journal stream, but not this process's stderr
    assert _stderr_of(tmp_path, other).splitlines() == plain
