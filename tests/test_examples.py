"""Every program in docs/examples/, run as a user runs them: a child process against a real
``busgate demo``, to the end, with what they print checked (the README's program and the
manual's other blocks: tests/test_docs.py).

One demo serves the module (starting one costs seconds); the programs run one after another,
each leaving the devices movable (the e-stop example resets them).
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import busgate.client as bc

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "docs" / "examples"
RUN_TIMEOUT_S = 60.0  # a hang guard, not a speed requirement


@pytest.fixture(scope="module")
def demo_endpoint(module_demo) -> str:
    """Where the module's demo (``conftest.module_demo``) serves."""
    return module_demo.endpoint


def run(program: Path, *args: str) -> str:
    done = subprocess.run([sys.executable, str(program), *args], capture_output=True,
                          text=True, timeout=RUN_TIMEOUT_S)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_every_example_is_run_here() -> None:
    tested = set(re.findall(r'"(\w+\.py)"', Path(__file__).read_text()))
    assert {path.name for path in EXAMPLES.glob("*.py")} == tested


def test_state_and_move(demo_endpoint) -> None:
    out = run(EXAMPLES / "state_and_move.py", demo_endpoint)
    assert "demo/la1 (inspire_la) at" in out
    assert "target now 1500" in out
    assert "refused: out_of_range" in out


def test_claim_and_follow_ends_its_stream_without_a_stale_event(demo_endpoint) -> None:
    events: list[dict] = []
    lock = threading.Lock()

    def heard(key: str, body: object) -> None:
        if isinstance(body, dict) and body.get("device") == "la1":
            with lock:
                events.append(body)

    with bc.connect(demo_endpoint, client_id="example-watcher") as watcher:
        watcher.subscribe("busgate/demo/events", heard)
        out = run(EXAMPLES / "claim_and_follow.py", demo_endpoint, "1.5")
        assert re.search(r"streamed 1\.5 s; la1 at \d+ \(target \d+\)", out)
        watcher.device("demo/la1").state(max_age=0)  # one more round of publication
    types = [event["type"] for event in events]
    assert "claimed" in types and "released" in types
    assert "stream_stopped" in types and "stream_stale" not in types


def test_group_move(demo_endpoint) -> None:
    out = run(EXAMPLES / "group_move.py", demo_endpoint)
    assert "demo/uart0 speaks inspire_la" in out
    assert "la1 reports target 300" in out and "la3 reports target 1500" in out


def test_estop_and_recovery(demo_endpoint) -> None:
    """The example leaves no device of the demo e-stopped: a newcomer's demo had seven of
    nine stopped after it, with nothing telling how to undo it."""
    out = run(EXAMPLES / "estop_and_recovery.py", demo_endpoint)
    assert "refused: la1 is e-stopped" in out
    assert "la1 moves again: True" in out and "demo reset" in out
    with bc.connect(demo_endpoint, client_id="examples-check") as c:
        deadline = time.monotonic() + 5.0
        while (stopped := [d.name for d in c.devices() if d.state and d.state.estopped]):
            assert time.monotonic() < deadline, f"still e-stopped: {stopped}"
            time.sleep(0.1)


def test_asyncio_follow(demo_endpoint) -> None:
    out = run(EXAMPLES / "asyncio_follow.py", demo_endpoint, "1")
    assert re.search(r"streamed 1 s; then \d+ states in 0\.5 s", out)
