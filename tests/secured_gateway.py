"""The daemon under deploy/zenoh/busgate.json5 (TLS, user names and passwords, access
control) as its clients reach it, for tests/test_deploy.py (raw zenoh sessions) and
tests/test_client_resilience.py (the SDK): the certificates, the accounts, and ``busgate run``
(a ROS 2 node too) on an Inspire LA simulator (``secured_daemon_serving``, conftest's
``secured_daemon``)."""

from __future__ import annotations

import ctypes
import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port

ZENOH = Path(__file__).resolve().parent.parent / "deploy" / "zenoh" / "busgate.json5"
#: The accounts of the daemon's password file: ``operator`` may command, ``viewer`` only read.
ACCOUNTS = {"operator": "op-secret", "viewer": "view-secret"}


def _openssl(*args: str | Path) -> None:
    subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True)


def _certificates(directory: Path) -> None:
    """A CA, and a certificate for 127.0.0.1 it signed: the files the json5 names."""
    directory.mkdir()
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    _openssl("req", "-x509", *ec, "-keyout", directory / "ca.key", "-out", directory / "ca.pem",
             "-days", "2", "-subj", "/CN=busgate test CA",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign")
    _openssl("req", *ec, "-keyout", directory / "busgate.key", "-out", directory / "busgate.csr",
             "-subj", "/CN=localhost")
    (directory / "ext.cnf").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n"
                                       "basicConstraints=CA:FALSE\n")
    _openssl("x509", "-req", "-in", directory / "busgate.csr", "-CA", directory / "ca.pem",
             "-CAkey", directory / "ca.key", "-CAcreateserial", "-days", "2",
             "-out", directory / "busgate.pem", "-extfile", directory / "ext.cnf")


#: ``busgate run`` as systemd would start it with MemoryDenyWriteExecute=yes: the kernel's
#: PR_SET_MDWE refuses writable-and-executable memory for the rest of the process's life, the
#: same promise the unit's seccomp filter enforces.
MDWE_PRELUDE = """
import ctypes, mmap, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
    sys.exit(f"PR_SET_MDWE refused: errno {ctypes.get_errno()}")
try:
    mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    sys.exit("a writable and executable mapping was allowed")
except PermissionError:
    pass
from busgate.gateway.cli import main
"""
MDWE_RUN = MDWE_PRELUDE + 'sys.exit(main(["run", "--config", sys.argv[1]]))\n'


def _kernel_has_mdwe() -> bool:
    libc = ctypes.CDLL(None, use_errno=True)
    return libc.prctl(66, 0, 0, 0, 0) >= 0  # PR_GET_MDWE: EINVAL before Linux 6.3


@dataclass
class SecuredGateway:
    """The daemon under deploy/zenoh/busgate.json5, as its clients reach it."""

    etc: Path
    port: int
    simulator: SerialSimulator
    sessions: list[zenoh.Session] = field(default_factory=list)

    def connect(self, user: str | None = None, password: str | None = None, *,
                scheme: str = "tls", mode: str = "client",
                insist: bool = False) -> zenoh.Session:
        """A session to the gateway's port (with no usrpwd when ``user`` is None), closed after
        the test; ``zenoh.ZError`` when zenoh cannot open it. A peer makes its connection in
        the background unless it must ``insist``: then opening it waits for the attempt and
        fails with it, as a client's does."""
        config = session_config(mode=mode, connect=[f"{scheme}/127.0.0.1:{self.port}"])
        if insist:
            config.insert_json5("connect/exit_on_failure", "true")
            config.insert_json5("connect/timeout_ms", "0")
        config.insert_json5("transport/link/tls/root_ca_certificate",
                            json.dumps(str(self.etc / "tls/ca.pem")))
        if user is not None:
            config.insert_json5("transport/auth/usrpwd",
                                json.dumps({"user": user, "password": password}))
        self.sessions.append(zenoh.open(config))
        return self.sessions[-1]

    def close_sessions(self) -> None:
        while self.sessions:
            self.sessions.pop().close()


#: ``reply_margin_ms``: the simulator shares the test's process and this machine's two busy
#: cores, so a scheduling hiccup of a few ms must not pass for a lost reply. ``[ros2]`` with
#: its defaults (domain 0, node ``busgate_gw1``: the names the json5's ROS rules are written
#: for); la1 has no joint table, so in ROS it is the raw joint ``la1``.
GATEWAY_TOML = """
[gateway]
name = "gw1"

[zenoh]
config_file = "{config_file}"
listen = ["{endpoint}"]

[ros2]

[[buses]]
name = "uart0"
transport = "serial"
port = "{port}"
baudrate = 921600
reply_margin_ms = 10

[[buses.devices]]
name = "la1"
kind = "inspire_la"
id = 1
poll_hz = 20
"""


def _wait_listening(daemon: subprocess.Popen, port: int) -> None:
    deadline = time.monotonic() + 20
    while True:
        assert daemon.poll() is None, "the daemon exited"
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            assert time.monotonic() < deadline, "the daemon does not listen"
            time.sleep(0.05)


def secured_daemon_serving(tmp_path_factory) -> Iterator[SecuredGateway]:
    """``busgate run`` (under PR_SET_MDWE where the kernel has it) on the LA simulator, its
    zenoh session from deploy/zenoh/busgate.json5 with the files moved under a scratch /etc
    (the users of ``ACCOUNTS``), until the generator is closed: the body of conftest's
    module-scoped ``secured_daemon`` fixture, as each start costs seconds."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed here (needed to make test certificates)")
    etc = tmp_path_factory.mktemp("etc")
    _certificates(etc / "tls")
    (etc / "zenoh-users.txt").write_text("".join(f"{u}:{p}\n" for u, p in ACCOUNTS.items()))
    json5 = etc / "zenoh.json5"
    json5.write_text(ZENOH.read_text().replace("/etc/busgate/", f"{etc}/"))
    port = unused_loopback_port()  # conftest's ``free_port`` is per test
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        toml = etc / "busgate.toml"
        toml.write_text(GATEWAY_TOML.format(config_file=json5, endpoint=f"tls/127.0.0.1:{port}",
                                            port=simulator.port))
        command = ([sys.executable, "-c", MDWE_RUN, str(toml)] if _kernel_has_mdwe()
                   else [sys.executable, "-m", "busgate.gateway.cli", "run", "--config", str(toml)])
        log = etc / "daemon.log"  # a file, not a pipe: nobody reads it while the module runs
        with log.open("w") as stderr:
            daemon = subprocess.Popen(command, stderr=stderr)
        gateway = SecuredGateway(etc, port, simulator)
        try:
            _wait_listening(daemon, port)
            yield gateway
        finally:
            gateway.close_sessions()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(timeout=20)
        assert daemon.returncode == 0, log.read_text()
