"""Shared test machinery. ``golden`` is h11's ``tr()`` for our byte-stream decoders: it runs a
manual's example frame through a fresh decoder whole, split at every byte, byte by byte, behind
garbage and after a copy of itself with a bad checksum."""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import pytest

from busgate.codecs.framing import ChecksumMismatch, Discarded, StreamDecoder

ERROR_EVENTS = (Discarded, ChecksumMismatch)


def _drain_after_feeding(make_decoder: Callable[[], StreamDecoder], chunks: Sequence[bytes]):
    decoder = make_decoder()
    events = []
    for chunk in chunks:
        decoder.feed(chunk)
        events.extend(decoder.events())
    assert decoder.pending < decoder.max_frame
    return events


def _without_errors(events):
    return [e for e in events if not isinstance(e, ERROR_EVENTS)]


def check_golden(
    make_decoder: Callable[[], StreamDecoder],
    wire: bytes,
    expected: Sequence[object],
    *,
    garbage: bytes = b"\x00\x13\x37",
) -> None:
    """Assert that ``wire`` decodes to exactly ``expected`` however it arrives."""
    expected = list(expected)
    assert _drain_after_feeding(make_decoder, [wire]) == expected, "whole"
    for k in range(1, len(wire)):
        assert _drain_after_feeding(make_decoder, [wire[:k], wire[k:]]) == expected, f"split {k}"
    assert _drain_after_feeding(make_decoder, [bytes([b]) for b in wire]) == expected, "bytewise"

    after_garbage = _drain_after_feeding(make_decoder, [garbage + wire])
    assert _without_errors(after_garbage) == expected, "after garbage"
    discarded = b"".join(e.data for e in after_garbage if isinstance(e, Discarded))
    assert discarded == garbage, "garbage reported as discarded"

    bad = wire[:-1] + bytes([wire[-1] ^ 0x5A])
    after_bad = _drain_after_feeding(make_decoder, [bad + wire])
    assert any(isinstance(e, ChecksumMismatch) for e in after_bad), "bad checksum reported"
    good = _without_errors(after_bad)
    assert good[len(good) - len(expected) :] == expected, "after a bad checksum"


@pytest.fixture
def golden() -> Callable[..., None]:
    """``golden(make_decoder, wire, expected, garbage=...)``: see ``check_golden``."""
    return check_golden


def wait_until(predicate: Callable[[], object], timeout: float = 5.0,
               what: str = "condition") -> None:
    """Poll ``predicate`` until it is true; fail the test after ``timeout`` seconds, saying
    ``what`` was awaited."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"{what}: not reached in {timeout} s"
        time.sleep(0.01)


@pytest.fixture
def wait_for() -> Callable[..., None]:
    """``wait_for(predicate, timeout=5.0)``: see ``wait_until``."""
    return wait_until


def _received_and_sent(simulator, since: int) -> tuple[list, list[int]]:
    """The simulator's records, and the indexes of those after ``since`` it received."""
    records = list(simulator.recorder.records)
    return records, [i for i, r in enumerate(records) if i >= since and r.direction == "rx"]


def sent_before_proof(
    simulator, since: int, frames: int, prove: Callable[[], object], timeout: float = 10.0
) -> list:
    """What ``simulator`` sent in answer to the ``frames`` frames the host wrote after record
    index ``since``, known once it answered a proof of life written after them: ``prove()``
    makes one exchange that is answered (writes a frame and reads its reply back). A simulator
    takes frames in wire order and records each reply as it sends it, before it reads the
    next frame: the replies between the first of those frames and the proof are theirs, so
    ``[]`` proves they went unanswered, with no sleep that a slow machine could outlast (a
    reply to an earlier frame, recorded a moment after ``since``, comes before the first)."""
    prove()
    found: list[list] = []

    def proof_answered() -> bool:
        records, received = _received_and_sent(simulator, since)
        if len(received) <= frames:
            return False
        first, proof = received[0], received[frames]
        if not any(r.direction == "tx" for r in records[proof + 1 :]):
            return False
        found[:] = [[r for r in records[first:proof] if r.direction == "tx"]]
        return True

    wait_until(proof_answered, timeout)
    return found[0]


def reply_after(simulator, since: int, timeout: float = 10.0):
    """The first reply ``simulator`` sends to a frame received after record index ``since``
    (waited for): what the host is about to read, byte for byte, noise and all."""
    found: list = []

    def replied() -> bool:
        records, received = _received_and_sent(simulator, since)
        sent = [r for r in records[received[0] :] if r.direction == "tx"] if received else []
        found[:] = sent[:1]
        return bool(sent)

    wait_until(replied, timeout)
    return found[0]


@pytest.fixture
def before_proof() -> Callable[..., list]:
    """``before_proof(simulator, since, frames, prove)``: see ``sent_before_proof``."""
    return sent_before_proof


@pytest.fixture
def next_reply() -> Callable[..., object]:
    """``next_reply(simulator, since)``: see ``reply_after``."""
    return reply_after


#: Where ``unused_loopback_port`` looks: below Linux's ephemeral range (32768–60999), which
#: the kernel gives to every ``bind`` to port 0 (a demo's dashboard at ``127.0.0.1:0``) and
#: every outgoing connection. A port taken from that range and freed for a zenoh listener to
#: take later could be handed to one of those meanwhile: a CI run's demo found its dashboard's
#: port in use at its ``listen``.
TEST_PORTS = range(20_000, 32_000)
_port_picks = random.Random(os.getpid())


def unused_loopback_port() -> int:
    """A TCP port on 127.0.0.1 nothing is bound to now (for zenoh and metrics endpoints),
    from ``TEST_PORTS``."""
    while True:
        port = _port_picks.choice(TEST_PORTS)
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port


@contextmanager
def silent_listener() -> Iterator[tuple[socket.socket, str]]:
    """A loopback TCP listener that takes connections and never speaks (a port some other
    program holds, a router that hangs), and its zenoh endpoint; its ``accept()`` returns once
    a connection came (30 s at most: a hang guard)."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        listener.settimeout(30.0)
        yield listener, f"tcp/127.0.0.1:{listener.getsockname()[1]}"


def status_once_signalled(process: subprocess.Popen, listener: socket.socket) -> int | None:
    """Once ``process`` connected to ``listener`` (a ``silent_listener``: zenoh waits for it
    10 s), SIGTERM: its exit status within 5 s, ``None`` when it still runs then."""
    held, _ = listener.accept()
    with held:
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            return None


@pytest.fixture
def free_port() -> Callable[[], int]:
    """``free_port()``: see ``unused_loopback_port``."""
    return unused_loopback_port


def may_run_realtime() -> bool:
    """Whether a process started here may ask for SCHED_FIFO (root, or ``RLIMIT_RTPRIO``)."""
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


#: How a test says it was skipped for want of a tool (systemd-analyze, openssl …).
MISSING_TOOL = "not installed here"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under CI (``CI=true``), which installs every tool the tests use, a test skipped for
    want of one fails: a missing install step must not pass as a skip."""
    outcome = yield
    report = outcome.get_result()
    if os.environ.get("CI") == "true" and report.skipped and MISSING_TOOL in str(report.longrepr):
        report.outcome = "failed"
        report.longrepr = f"skipped under CI, which installs every tool: {report.longrepr}"


# -- gateways as child processes, started once per module (each start costs seconds) ---------
# The test-helper modules are imported inside the fixtures: tests/test_ci_rules.py runs this
# file's text in a scratch directory where ``tests`` is no package.


@pytest.fixture(scope="module")
def module_demo():
    """``busgate demo`` on a free loopback port for the whole module (``.endpoint``), stopped
    after it; a test that e-stops or claims leaves its devices enabled and unclaimed."""
    from tests.gateway_process import DemoProcess

    demo = DemoProcess(f"tcp/127.0.0.1:{unused_loopback_port()}")
    try:
        yield demo
    finally:
        assert demo.terminate() == 0


@pytest.fixture(scope="module")
def secured_daemon(tmp_path_factory):
    """``busgate run`` under deploy/zenoh/busgate.json5 (TLS, passwords, ACL) on an LA
    simulator, for the whole module: ``tests.secured_gateway.secured_daemon_serving``."""
    from tests.secured_gateway import secured_daemon_serving

    yield from secured_daemon_serving(tmp_path_factory)
