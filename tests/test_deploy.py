"""deploy/: every file is there and is what its tool accepts, checked with the tool itself
wherever this machine has it: the unit with ``systemd-analyze verify`` and ``security
--offline``, the .network against systemd-networkd's own key table, sysusers.d and tmpfiles.d by
applying them to a scratch root, the zenoh config by opening the real daemon with it (TLS,
passwords, access control), and MemoryDenyWriteExecute= by running the daemon under the
kernel's equivalent (PR_SET_MDWE)."""

from __future__ import annotations

import ctypes
import json
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.zenoh_config import session_config

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
UNIT = DEPLOY / "busgate.service"
NETWORK = DEPLOY / "systemd-networkd" / "80-can0.network"
RULES = DEPLOY / "udev" / "99-busgate.rules"
SYSUSERS = DEPLOY / "sysusers.d" / "busgate.conf"
TMPFILES = DEPLOY / "tmpfiles.d" / "busgate.conf"
ZENOH = DEPLOY / "zenoh" / "busgate.json5"
NETWORKD = Path("/lib/systemd/systemd-networkd")


def unit_options(path: Path) -> dict[str, dict[str, list[str]]]:
    """A systemd unit as ``{section: {key: [values, in order]}}`` (keys may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    section = None
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = sections.setdefault(line.strip("[]"), {})
            continue
        key, _, value = line.partition("=")
        assert section is not None and key, f"{path.name}: {line!r} outside a section"
        section.setdefault(key.strip(), []).append(value.strip())
    return sections


def test_every_deploy_file_is_there() -> None:
    for path in (UNIT, NETWORK, RULES, SYSUSERS, TMPFILES, ZENOH):
        assert path.is_file() and path.read_text().strip(), path


def test_the_unit_has_every_option_the_issue_names() -> None:
    service = unit_options(UNIT)["Service"]
    expected = {
        "Type": ["notify"], "Restart": ["on-failure"], "User": ["busgate"],
        "SupplementaryGroups": ["dialout"], "ProtectSystem": ["strict"],
        "ProtectHome": ["yes"], "PrivateTmp": ["yes"], "NoNewPrivileges": ["yes"],
        "ProtectKernelTunables": ["yes"], "ProtectKernelModules": ["yes"],
        "ProtectKernelLogs": ["yes"], "ProtectControlGroups": ["yes"],
        "RestrictNamespaces": ["yes"], "LockPersonality": ["yes"],
        "MemoryDenyWriteExecute": ["yes"], "SystemCallFilter": ["@system-service"],
        "CapabilityBoundingSet": [""], "DevicePolicy": ["closed"],
    }
    for key, values in expected.items():
        assert service.get(key) == values, key
    assert service["WatchdogSec"] and service["LimitRTPRIO"]
    assert service["ExecStart"][0].split()[1:] == ["run", "--config", "/etc/busgate/busgate.toml"]
    assert set(service["RestrictAddressFamilies"][0].split()) == {
        "AF_CAN", "AF_NETLINK", "AF_UNIX", "AF_INET", "AF_INET6"}
    assert {"char-ttyUSB rw", "char-ttyACM rw", "char-ttyS rw"} <= set(service["DeviceAllow"])
    assert "RestrictRealtime" not in service, "SCHED_FIFO for the bus threads needs realtime"


def _scratch_root(tmp_path: Path) -> Path:
    """A root holding the unit, its ExecStart and the host's units it refers to."""
    root = tmp_path / "root"
    executable = root / unit_options(UNIT)["Service"]["ExecStart"][0].split()[0].lstrip("/")
    executable.parent.mkdir(parents=True)
    executable.write_text("#!/bin/sh\n")
    executable.chmod(0o755)
    (root / "etc/systemd/system").mkdir(parents=True)
    shutil.copy(UNIT, root / "etc/systemd/system")
    shutil.copytree("/usr/lib/systemd/system", root / "usr/lib/systemd/system", symlinks=True)
    return root


needs_systemd_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None or not Path("/usr/lib/systemd/system").is_dir(),
    reason="systemd-analyze is not installed here (apt-get install systemd)")


@needs_systemd_analyze
def test_systemd_analyze_verify_is_clean(tmp_path) -> None:
    root = _scratch_root(tmp_path)
    result = subprocess.run(["systemd-analyze", "verify", f"--root={root}", "busgate.service"],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0 and not (result.stdout + result.stderr).strip(), result


@needs_systemd_analyze
def test_systemd_analyze_security_exposure_is_2_5_or_better() -> None:
    result = subprocess.run(["systemd-analyze", "security", "--offline=true", "--no-pager",
                             str(UNIT)], capture_output=True, text=True, check=False)
    found = re.search(r"Overall exposure level for busgate\.service: (\d+\.\d)", result.stdout)
    assert found, result
    assert float(found.group(1)) <= 2.5, result.stdout


@pytest.mark.skipif(not NETWORKD.is_file(), reason="systemd-networkd is not installed here")
def test_the_can_network_uses_only_keys_networkd_knows() -> None:
    table = NETWORKD.read_bytes()
    options = unit_options(NETWORK)
    assert options["Match"]["Name"] == ["can0"]
    assert options["CAN"]["BitRate"] == ["500K"] and options["CAN"]["RestartSec"]
    for section, keys in options.items():
        for key in keys:
            assert f"{section}.{key}\0".encode() in table, f"networkd knows no {section}.{key}"


UDEV_TOKEN = re.compile(r'^([A-Z_]+)(\{[^}]+\})?(==|!=|\+=|:=|=)"[^"]*"$')


def test_the_udev_rules_are_well_formed_and_do_what_the_issue_asks() -> None:
    rules = [line for line in RULES.read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    for rule in rules:
        for token in re.split(r",\s*", rule):
            assert UDEV_TOKEN.match(token), f"{token!r} in {rule!r}"
    named = [rule for rule in rules if 'SYMLINK+="busgate/' in rule]
    assert {"0403", "1a86", "067b", "16d0"} <= {
        re.search(r'idVendor}=="(\w+)"', rule).group(1) for rule in named}
    for rule in named:
        assert 'GROUP="dialout"' in rule and 'ENV{ID_MM_DEVICE_IGNORE}="1"' in rule, rule
    assert any('DRIVER=="ftdi_sio"' in r and 'ATTR{latency_timer}="1"' in r for r in rules)


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None
                    or shutil.which("systemd-tmpfiles") is None,
                    reason="systemd-sysusers/systemd-tmpfiles are not installed here")
def test_sysusers_and_tmpfiles_create_the_user_and_the_config_directory(tmp_path) -> None:
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    (root / "etc/passwd").write_text("root:x:0:0:root:/root:/bin/sh\n")
    (root / "etc/group").write_text("root:x:0:\ndialout:x:20:\n")
    subprocess.run(["systemd-sysusers", f"--root={root}", str(SYSUSERS)], check=True,
                   capture_output=True)
    assert re.search(r"^busgate:x:\d+:\d+:busgate gateway:", (root / "etc/passwd").read_text(),
                     re.M)
    assert re.search(r"^dialout:x:20:busgate$", (root / "etc/group").read_text(), re.M)
    subprocess.run(["systemd-tmpfiles", f"--root={root}", "--create", str(TMPFILES)],
                   check=True, capture_output=True)
    config_dir = (root / "etc/busgate").stat()
    assert oct(config_dir.st_mode & 0o777) == "0o750" and config_dir.st_uid == 0


# -- the zenoh config: TLS, user/password, access control, with the real daemon -----------


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


def test_the_zenoh_config_loads_in_zenoh() -> None:
    config = json.loads(str(zenoh.Config.from_file(str(ZENOH))))
    assert config["access_control"]["enabled"] is True
    assert config["transport"]["auth"]["usrpwd"]["dictionary_file"].startswith("/etc/busgate/")


#: ``busgate run`` as systemd would start it with MemoryDenyWriteExecute=yes: the kernel's
#: PR_SET_MDWE refuses writable-and-executable memory for the rest of the process's life, the
#: same promise the unit's seccomp filter enforces.
MDWE_RUN = """
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
sys.exit(main(["run", "--config", sys.argv[1]]))
"""


def _kernel_has_mdwe() -> bool:
    libc = ctypes.CDLL(None, use_errno=True)
    return libc.prctl(66, 0, 0, 0, 0) >= 0  # PR_GET_MDWE: EINVAL before Linux 6.3


@pytest.fixture
def secured_gateway(tmp_path):
    """``busgate run`` (under PR_SET_MDWE where the kernel has it) on the LA simulator, its
    zenoh session from deploy/zenoh/busgate.json5 with the files moved under tmp_path; yields
    ``connect(user, password)`` for client sessions."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed here (needed to make test certificates)")
    etc = tmp_path / "etc"
    etc.mkdir()
    _certificates(etc / "tls")
    (etc / "zenoh-users.txt").write_text("operator:op-secret\nviewer:view-secret\n")
    json5 = etc / "zenoh.json5"
    json5.write_text(ZENOH.read_text().replace("/etc/busgate/", f"{etc}/"))
    port = _free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    sessions: list[zenoh.Session] = []

    def connect(user: str, password: str) -> zenoh.Session:
        config = session_config(mode="client", connect=[endpoint])
        config.insert_json5("transport/link/tls/root_ca_certificate",
                            json.dumps(str(etc / "tls/ca.pem")))
        config.insert_json5("transport/auth/usrpwd",
                            json.dumps({"user": user, "password": password}))
        sessions.append(zenoh.open(config))
        return sessions[-1]

    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        toml = etc / "busgate.toml"
        toml.write_text(GATEWAY_TOML.format(config_file=json5, endpoint=endpoint,
                                            port=simulator.port))
        command = ([sys.executable, "-c", MDWE_RUN, str(toml)] if _kernel_has_mdwe()
                   else [sys.executable, "-m", "busgate.gateway.cli", "run", "--config", str(toml)])
        daemon = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
        try:
            _wait_listening(daemon, port)
            yield connect
        finally:
            for session in sessions:
                session.close()
            daemon.send_signal(signal.SIGTERM)
            _, stderr = daemon.communicate(timeout=20)
        assert daemon.returncode == 0, stderr


GATEWAY_TOML = """
[gateway]
name = "gw1"

[zenoh]
config_file = "{config_file}"
listen = ["{endpoint}"]

[[buses]]
name = "uart0"
transport = "serial"
port = "{port}"
baudrate = 921600

[[buses.devices]]
name = "la1"
kind = "inspire_la"
id = 1
poll_hz = 20
"""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


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


def _answers(session: zenoh.Session, key: str, payload: str = "", timeout: float = 2.0) -> list:
    replies = session.get(key, payload=payload, timeout=timeout)
    return [json.loads(reply.ok.payload.to_bytes()) for reply in replies if reply.ok]


def _until_answered(session: zenoh.Session, key: str, payload: str = "") -> list:
    deadline = time.monotonic() + 20
    while not (answers := _answers(session, key, payload)):
        assert time.monotonic() < deadline, f"no answer on {key}"
    return answers


def test_operators_command_everyone_reads_telemetry(secured_gateway) -> None:
    operator = secured_gateway("operator", "op-secret")
    viewer = secured_gateway("viewer", "view-secret")
    states = []
    viewer.declare_subscriber("busgate/*/dev/*/state", lambda sample: states.append(sample))
    info = _until_answered(viewer, "busgate/gw1/info")  # the daemon is up, the viewer reads
    assert info[0]["ok"] is True
    status = json.dumps({"op": "status"})
    reply = _until_answered(operator, "busgate/gw1/dev/la1/cmd", status)
    assert reply[0]["ok"] is True, reply
    assert _answers(viewer, "busgate/gw1/dev/la1/cmd", status) == [], "a viewer commanded"
    deadline = time.monotonic() + 20
    while not states:
        assert time.monotonic() < deadline, "the viewer got no telemetry"
        time.sleep(0.05)


def test_a_wrong_password_gets_no_session(secured_gateway) -> None:
    with pytest.raises(zenoh.ZError):
        secured_gateway("operator", "guess")
