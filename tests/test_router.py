"""``busgate router``: a zenoh router from the Python binding, as real processes on explicit
loopback endpoints (multicast scouting off everywhere, no address but 127.0.0.1): a gateway
and a client, both in client mode and listening nowhere, meet only through it; SIGTERM and
SIGINT end it with exit 0; every refusal is one line and exit status 2; a ``--config`` file is
laid underneath (its id shows, its mode and listen endpoints give way to the command line's);
and it runs under the kernel's MemoryDenyWriteExecute (deploy/busgate-router.service)."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

import busgate.client as bc
from busgate.codecs import inspire_la as la
from busgate.gateway.cli import main
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.zenoh_session import session_config
from tests.conftest import silent_listener, status_once_signalled, unused_loopback_port
from tests.gateway_process import BUSGATE, TIMEOUT_S, GatewayProcess, run_busgate, serial_bus
from tests.secured_gateway import MDWE_PRELUDE, _kernel_has_mdwe

SERVING = re.compile(r"^busgate router: serving on (?P<where>.+) \(zenoh (?P<version>\S+), "
                     r"id (?P<zid>[0-9a-f]+)\)$")
#: The children's environment: zenoh's own log, which RUST_LOG would turn on, kept off.
QUIET = {key: value for key, value in os.environ.items() if key != "RUST_LOG"}
#: The router's code under PR_SET_MDWE (what MemoryDenyWriteExecute=yes enforces), as in
#: tests/secured_gateway.py for the daemon.
MDWE_ROUTER = MDWE_PRELUDE + 'sys.exit(main(["router", *sys.argv[1:]]))\n'


def loopback() -> str:
    return f"tcp/127.0.0.1:{unused_loopback_port()}"


class RouterProcess:
    """``busgate router ARGS`` as a child (or ``argv``, a command line that runs it),
    returned once it printed its serving line (``serving``, matched by ``SERVING``); stopped
    by its PID, with a signal."""

    def __init__(self, *args: str, argv: list[str] | None = None) -> None:
        self.process = subprocess.Popen(argv or [*BUSGATE, "router", *args],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        text=True, env=QUIET)
        self._stdout: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        try:
            line = self._stdout.get(timeout=TIMEOUT_S)
        except queue.Empty:
            self.process.kill()
            raise
        if not line:
            self.process.wait(timeout=TIMEOUT_S)
            pytest.fail(f"the router ended before it served: {self.process.stderr.read()!r}")
        self.serving = SERVING.match(line.rstrip("\n"))
        assert self.serving, line

    def _read(self) -> None:
        for line in self.process.stdout:
            self._stdout.put(line)
        self._stdout.put("")  # end of output

    def stop(self, signum: int = signal.SIGTERM) -> int:
        """Send ``signum`` (if it still runs) and wait for its end: its exit status. It
        printed nothing after its serving line, on stdout or stderr."""
        if self.process.poll() is None:
            self.process.send_signal(signum)
        status = self.process.wait(timeout=TIMEOUT_S)
        assert self._stdout.get(timeout=TIMEOUT_S) == "", "it printed after serving"
        assert self.process.stderr.read() == "", "it logged"
        return status


@pytest.fixture
def start_router():
    """``start_router(*args)``: a ``RouterProcess``; any still running after the test is
    killed (by its PID) and its exit status checked by the test that cares."""
    started: list[RouterProcess] = []

    def start(*args: str, **options) -> RouterProcess:
        router = RouterProcess(*args, **options)
        started.append(router)
        return router

    yield start
    for router in started:
        if router.process.poll() is None:
            router.process.kill()
            router.process.wait(timeout=TIMEOUT_S)


def client_session(endpoint: str) -> zenoh.Session:
    """A bare zenoh session in client mode, listening nowhere, connected to ``endpoint``."""
    return zenoh.open(session_config(mode="client", connect=[endpoint]))


# -- the router joins a gateway and a client ----------------------------------------------


def test_a_gateway_and_a_client_meet_only_through_the_router(
    start_router, tmp_path, wait_for
) -> None:
    """Both sessions are clients (zenoh clients talk to a router, never to each other) and
    listen nowhere: the gateway's info and the actuator's state reach the client through the
    router, and stop reaching it once the router is gone."""
    endpoint = loopback()
    router = start_router("--listen", endpoint)
    assert router.serving["where"] == endpoint
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        config = tmp_path / "gw1.toml"
        config.write_text(f'[gateway]\nname = "gw1"\n[zenoh]\nmode = "client"\n'
                          f'connect = ["{endpoint}"]\nlisten = []\n'
                          + serial_bus("uart0", simulator.port, "la1"))
        gateway = GatewayProcess(config, env=QUIET)
        try:
            gateway.wait_for("serving")
            with bc.connect([endpoint], client_id="router-test", mode="client") as client:
                wait_for(lambda: "gw1" in client.gateways(), timeout=TIMEOUT_S)
                assert client.gateways()["gw1"]["buses"], client.gateways()
                state = client.device("gw1/la1").state(timeout=TIMEOUT_S)
                assert state.position is not None
                assert router.stop() == 0
                wait_for(lambda: client.gateways() == {}, timeout=TIMEOUT_S)
        finally:
            assert gateway.stop() == 0, gateway.lines


# -- how it stops -------------------------------------------------------------------------


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_sigterm_and_sigint_each_end_it_with_exit_0(start_router, signum) -> None:
    endpoint = loopback()
    router = start_router("--listen", endpoint)
    session = client_session(endpoint)  # it serves: a client session needs its router
    try:
        assert [str(zid) for zid in session.info.routers_zid()] == [router.serving["zid"]]
    finally:
        session.close()
    assert router.stop(signum) == 0


def test_a_router_it_connects_to_that_never_answers_holds_its_stop_a_second_at_most(
        start_router, tmp_path) -> None:
    """zenoh's close waits for a connect under way, to an endpoint that took the connection
    and never answers for 10 s: all of the unit's ``TimeoutStopSec``."""
    with silent_listener() as (mute, endpoint):
        config = _file(tmp_path, "zenoh.json5", json.dumps({"connect": {"endpoints": [endpoint]}}))
        router = start_router("--listen", loopback(), "--config", config)
        assert status_once_signalled(router.process, mute) == 0  # its connect under way
    assert "did not close within 1 s" in router.process.stderr.read()


def test_a_client_gateway_that_starts_before_its_router_waits_for_it(start_router,
                                                                      tmp_path) -> None:
    """A robot that boots before its router: the gateway in client mode exited (exit 2), and
    after five starts systemd left the unit failed. It waits, saying so, and serves once the
    router is up; a stop while it waits is heard at once."""
    router = loopback()
    config = tmp_path / "gw.toml"
    config.write_text(f'[gateway]\nname = "early"\n[zenoh]\nmode = "client"\n'
                      f'connect = ["{router}"]\n'
                      + serial_bus("uart0", str(tmp_path / "none"), "la1"))
    gateway = GatewayProcess(config, env=QUIET)
    try:
        gateway.wait_for(f"no router reached at {router}: trying again every 2 s")
        serving = start_router("--listen", router)
        gateway.wait_for("gateway early serving 1 bus")
        session = client_session(router)
        try:  # every key served, the trajectory's too (its lanes outlived the tries)
            [reply] = session.get("busgate/early/trajectory", payload='{"op": "status"}',
                                  timeout=TIMEOUT_S)
            assert json.loads(reply.ok.payload.to_bytes()) == {"ok": True, "trajectories": []}
        finally:
            session.close()
        # The router goes and comes back: the journal tells both.
        assert serving.stop() == 0
        gateway.wait_for(f"zenoh: no router reached at {router} any more")
        serving = start_router("--listen", router)
        gateway.wait_for(f"zenoh: a router reached again at {router}, after ")
    finally:
        assert gateway.stop() == 0
    assert serving.stop() == 0
    waiting = GatewayProcess(config, env=QUIET)  # its router gone again
    try:
        waiting.wait_for("no router reached")
        waiting.process.send_signal(signal.SIGTERM)
        assert waiting.process.wait(timeout=TIMEOUT_S) == 0
        waiting.wait_for("gateway early stopped before its session opened")
    finally:
        waiting.stop()  # a test that fails leaves no gateway behind


# -- what it refuses ----------------------------------------------------------------------


@pytest.fixture
def port_in_use():
    """A loopback TCP port that something else listens on."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield holder.getsockname()[1]


def _file(tmp_path: Path, name: str, content: str | bytes) -> str:
    path = tmp_path / name
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return str(path)


#: Each refusal: its arguments (given tmp_path and a port in use) and what its line says
#: (``{port}``: that port).
REFUSALS: dict[str, tuple[Callable[[Path, int], list[str]], str]] = {
    "malformed endpoint": (lambda d, p: ["--listen", "nonsense"],
                           "--listen 'nonsense': Endpoints must be of the form"),
    "endpoint with no address": (lambda d, p: ["--listen", "tcp/"], "--listen 'tcp/'"),
    "port out of range": (lambda d, p: ["--listen", "tcp/127.0.0.1:99999"],
                          "--listen 'tcp/127.0.0.1:99999': port '99999' is no port: from 1 to "
                          "65535"),
    "port 0": (lambda d, p: ["--listen", "tcp/127.0.0.1:0"],
               "--listen 'tcp/127.0.0.1:0': port 0 is one zenoh picks and tells nobody"),
    "unknown protocol": (lambda d, p: ["--listen", "nosuch/127.0.0.1:7447"],
                         "cannot listen on nosuch/127.0.0.1:7447"),
    "port in use": (lambda d, p: ["--listen", f"tcp/127.0.0.1:{p}"],
                    "cannot listen on tcp/127.0.0.1:{port}: it is in use (another busgate "
                    "router, zenohd or gateway?)"),
    "second endpoint in use": (lambda d, p: ["--listen", loopback(), "--listen",
                                             f"tcp/127.0.0.1:{p}"],
                               "cannot listen on tcp/127.0.0.1:{port}: it is in use"),
    "missing config": (lambda d, p: ["--listen", loopback(), "--config", str(d / "no.json5")],
                       "no.json5: no such file"),
    "config is a directory": (lambda d, p: ["--listen", loopback(), "--config", str(d)],
                              ": not a file"),
    "config not json5": (lambda d, p: ["--listen", loopback(), "--config",
                                       _file(d, "bad.json5", "{ listen: ")],
                         "bad.json5: line 1, column 11: expected array"),
    "config key unknown": (lambda d, p: ["--listen", loopback(), "--config",
                                         _file(d, "typo.json5", '{\n  lisen: {},\n}\n')],
                           "typo.json5: line 2, column 3: unknown field `lisen`"),
    "config value of the wrong type": (lambda d, p: [
        "--listen", loopback(), "--config",
        _file(d, "type.json5", '{ listen: { endpoints: 5 } }')],
        "type.json5: line 1, column 24: invalid type: integer `5`"),
    "config not yaml": (lambda d, p: ["--listen", loopback(), "--config",
                                      _file(d, "bad.yaml", "mode: [\n  - x\n")],
                        "bad.yaml: line 1, column 7: mode: invalid type: sequence"),
    "config not toml": (lambda d, p: ["--listen", loopback(), "--config",
                                      _file(d, "bad.toml", "mode = \n")],
                        "bad.toml: string values must be quoted"),
    "config not text": (lambda d, p: ["--listen", loopback(), "--config",
                                      _file(d, "binary.json5", b"\xff\xfe\x00{")],
                        "binary.json5: stream did not contain valid UTF-8"),
    "tls with no key in the config": (lambda d, p: ["--listen", f"tls/127.0.0.1:{p}",
                                                    "--config", _file(d, "tls.json5", "{}")],
                                      "cannot listen on tls/127.0.0.1:{port}: Cannot create a "
                                      "new TLS listener on 127.0.0.1:{port}. Missing TLS "
                                      "private key"),
    "config empty": (lambda d, p: ["--listen", loopback(), "--config",
                                   _file(d, "empty.json5", "")], "empty.json5: Empty config"),
    "endpoint given twice": (lambda d, p: ["--listen", "tcp/127.0.0.1:7", "--listen",
                                           "tcp/127.0.0.1:7"],
                             "--listen tcp/127.0.0.1:7 is given twice"),
    "one port listened on twice": (lambda d, p: ["--listen", "tcp/0.0.0.0:7", "--listen",
                                                 "tcp/127.0.0.1:7"],
                                   "--listen tcp/0.0.0.0:7 and --listen tcp/127.0.0.1:7 take the "
                                   "same port"),
    "unix socket path on a file": (lambda d, p: ["--listen",
                                                 f"unixsock-stream/{_file(d, 'keep.conf', 'x')}"],
                                   "keep.conf exists and is not a socket (zenoh would delete it"),
    "config of no zenoh format": (lambda d, p: ["--listen", loopback(), "--config",
                                                _file(d, "zenoh.ini", "mode = router\n")],
                                  "zenoh.ini: Unsupported file type '.ini'"),
}


def check_refusal(status: int, stdout: str, stderr: str, expected: str) -> None:
    """Exit status 2, nothing on stdout, one line on stderr saying ``expected``, no
    traceback and no Rust source location."""
    assert status == 2, (status, stdout, stderr)
    assert stdout == ""
    [line] = stderr.splitlines()
    assert line.startswith("busgate router: error: "), line
    assert expected in line, line
    assert "Traceback" not in stderr and ".rs:" not in line, line


@pytest.mark.parametrize("case", REFUSALS.values(), ids=REFUSALS)
def test_a_refusal_is_one_line_and_exit_status_2(case, tmp_path, port_in_use, capsys) -> None:
    """Every refusal, through the command's ``main`` (the code a process runs, without a
    process start per case)."""
    arguments, expected = case
    status = main(["router", *arguments(tmp_path, port_in_use)])
    check_refusal(status, *capsys.readouterr(), expected.format(port=port_in_use))


#: One refusal of each kind (an endpoint zenoh cannot parse, one it cannot listen on, a
#: config file missing, one it cannot parse) from a real ``busgate router`` process.
AS_A_PROCESS = ["malformed endpoint", "port in use", "missing config", "config not json5"]


@pytest.mark.parametrize("name", AS_A_PROCESS)
def test_a_refusal_from_a_process_is_one_line_and_exit_status_2(
    name, tmp_path, port_in_use
) -> None:
    arguments, expected = REFUSALS[name]
    result = run_busgate("router", *arguments(tmp_path, port_in_use), env=QUIET)
    check_refusal(result.returncode, result.stdout, result.stderr,
                  expected.format(port=port_in_use))


def test_no_listen_endpoint_is_a_usage_error_no_silent_default(capsys) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["router"])
    assert exited.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err
    assert err.splitlines()[-1] == (
        "busgate router: error: the following arguments are required: --listen")


# -- the config file underneath -----------------------------------------------------------


def test_a_config_file_is_laid_underneath_the_command_line(start_router, tmp_path) -> None:
    """The file's id is the router's; its mode and its listen endpoints give way to
    ``router`` and ``--listen``: a client reaches the router on the command line's endpoint
    and nothing listens on the file's."""
    zid, endpoint, file_endpoint = "b05a7e00000000000000000000000001", loopback(), loopback()
    config = tmp_path / "zenoh.json5"
    config.write_text(json.dumps({"id": zid, "mode": "peer",
                                  "listen": {"endpoints": [file_endpoint]}}))
    router = start_router("--listen", endpoint, "--config", str(config))
    assert router.serving["zid"] == zid
    session = client_session(endpoint)
    try:
        assert [str(found) for found in session.info.routers_zid()] == [zid]
    finally:
        session.close()
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        client_session(file_endpoint)
    assert router.stop() == 0


# -- the command line and the unit --------------------------------------------------------


def test_the_help_names_zenohd_and_explicit_endpoints(capsys) -> None:
    assert main([]) == 2
    assert "\n    router " in capsys.readouterr().err
    with pytest.raises(SystemExit) as exited:
        main(["router", "--help"])
    assert exited.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "zenohd is the recommended router" in text
    assert "Multicast scouting is off" in text and '"client"' in text


@pytest.mark.skipif(not _kernel_has_mdwe(), reason="the kernel has no PR_SET_MDWE (Linux 6.3+)")
def test_it_serves_under_memory_deny_write_execute(start_router) -> None:
    """deploy/busgate-router.service has MemoryDenyWriteExecute=yes: the router and a
    session through it work under the kernel's equivalent (the daemon's own check:
    tests/secured_gateway.py)."""
    endpoint = loopback()
    router = start_router(argv=[sys.executable, "-c", MDWE_ROUTER, "--listen", endpoint])
    session = client_session(endpoint)
    try:
        session.put("busgate/router-test", b"through")
        assert [str(zid) for zid in session.info.routers_zid()] == [router.serving["zid"]]
    finally:
        session.close()
    assert router.stop() == 0
