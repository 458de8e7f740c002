"""deploy/: every file is there and is what its tool accepts, checked with the tool itself
wherever this machine has it: both units (the gateway's and the router's) with
``systemd-analyze verify`` and ``security --offline``, the .network against systemd-networkd's
own key table, sysusers.d and tmpfiles.d by applying them to a scratch root, the zenoh config by
opening the real daemon with it (TLS, passwords, access control), and MemoryDenyWriteExecute=
by running the daemon under the kernel's equivalent (PR_SET_MDWE; the router's:
tests/test_router.py)."""

from __future__ import annotations

import asyncio
import itertools
import json
import re
import shutil
import subprocess
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from busgate.codecs.ros2 import messages, rmw_zenoh
from busgate.gateway.api import bridge as bridge_module
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.cli import build_parser
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import RecorderSection
from tests.secured_gateway import ZENOH
from tests.test_base import BASE
from tests.test_base import config_of as base_config_of

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
UNIT = DEPLOY / "busgate.service"
ROUTER_UNIT = DEPLOY / "busgate-router.service"
UNITS = {path.name: path for path in (UNIT, ROUTER_UNIT)}
NETWORK = DEPLOY / "systemd-networkd" / "80-can0.network"
RULES = DEPLOY / "udev" / "99-busgate.rules"
SYSUSERS = DEPLOY / "sysusers.d" / "busgate.conf"
TMPFILES = DEPLOY / "tmpfiles.d" / "busgate.conf"
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
    for path in (UNIT, ROUTER_UNIT, NETWORK, RULES, SYSUSERS, TMPFILES, ZENOH):
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


def test_the_unit_lets_the_daemon_write_the_recorders_default_dir_and_nothing_else() -> None:
    service = unit_options(UNIT)["Service"]
    assert service["ProtectSystem"] == ["strict"]  # everything read-only ...
    [state] = service["StateDirectory"]  # ... but this one, made for the service's user
    assert "/var/lib/" + state == RecorderSection().dir
    for key in ("ReadWritePaths", "CacheDirectory", "LogsDirectory", "RuntimeDirectory"):
        assert key not in service, f"{key}= would let it write elsewhere"


#: The hardening both units share, option by option (the router needs no device, group or
#: realtime priority, so it adds to these rather than leaving any out).
SHARED_HARDENING = (
    "User", "Group", "UMask", "DevicePolicy", "CapabilityBoundingSet", "NoNewPrivileges",
    "ProtectSystem", "ProtectHome", "PrivateTmp", "ProtectProc", "ProtectKernelTunables",
    "ProtectKernelModules", "ProtectKernelLogs", "ProtectControlGroups", "ProtectClock",
    "ProtectHostname", "RemoveIPC", "PrivateMounts", "RestrictNamespaces", "LockPersonality",
    "MemoryDenyWriteExecute", "RestrictSUIDSGID", "SystemCallArchitectures",
    "SystemCallErrorNumber", "Restart", "StartLimitIntervalSec", "StartLimitBurst",
)


def test_the_router_unit_runs_busgate_router_hardened_as_the_gateways() -> None:
    options, gateway = unit_options(ROUTER_UNIT), unit_options(UNIT)
    service, gateway_service = options["Service"], gateway["Service"]
    program, *arguments = service["ExecStart"][0].split()
    assert program == gateway_service["ExecStart"][0].split()[0] == "/opt/busgate/bin/busgate"
    assert arguments == ["router", "--listen", "tcp/0.0.0.0:7447"]
    parsed = build_parser("router").parse_args(arguments)  # what the command line accepts
    assert parsed.listen == ["tcp/0.0.0.0:7447"] and parsed.config is None
    assert service["Type"] in (["simple"], ["exec"]), "the router does not speak sd_notify"
    for key in ("NotifyAccess", "WatchdogSec", "SupplementaryGroups", "DeviceAllow",
                "LimitRTPRIO"):
        assert key not in service, f"{key}= is the gateway's, not the router's"
    assert service["DevicePolicy"] == ["closed"] and service["PrivateDevices"] == ["yes"]
    assert service["RestrictRealtime"] == ["yes"]
    assert set(service["RestrictAddressFamilies"][0].split()) == {
        "AF_NETLINK", "AF_UNIX", "AF_INET", "AF_INET6"}
    assert service["SystemCallFilter"][0] == "@system-service"
    for key in SHARED_HARDENING:
        assert service.get(key, options["Unit"].get(key)) == gateway_service.get(
            key, gateway["Unit"].get(key)), key
    assert options["Install"] == gateway["Install"] == {"WantedBy": ["multi-user.target"]}
    header = ROUTER_UNIT.read_text().split("\n[Unit]", 1)[0]
    assert "zenohd is the recommended router" in header
    assert "install -m 644 deploy/busgate-router.service /etc/systemd/system/" in header
    assert "systemctl enable --now busgate-router" in header


def _scratch_root(tmp_path: Path, unit: Path) -> Path:
    """A root holding ``unit``, its ExecStart and the host's units it refers to."""
    root = tmp_path / "root"
    executable = root / unit_options(unit)["Service"]["ExecStart"][0].split()[0].lstrip("/")
    executable.parent.mkdir(parents=True)
    executable.write_text("#!/bin/sh\n")
    executable.chmod(0o755)
    (root / "etc/systemd/system").mkdir(parents=True)
    shutil.copy(unit, root / "etc/systemd/system")
    shutil.copytree("/usr/lib/systemd/system", root / "usr/lib/systemd/system", symlinks=True)
    return root


needs_systemd_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None or not Path("/usr/lib/systemd/system").is_dir(),
    reason="systemd-analyze is not installed here (apt-get install systemd)")


@needs_systemd_analyze
@pytest.mark.parametrize("name", UNITS)
def test_systemd_analyze_verify_is_clean(tmp_path, name) -> None:
    root = _scratch_root(tmp_path, UNITS[name])
    result = subprocess.run(["systemd-analyze", "verify", f"--root={root}", name],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0 and not (result.stdout + result.stderr).strip(), result


@needs_systemd_analyze
@pytest.mark.parametrize("name", UNITS)
def test_systemd_analyze_security_exposure_is_2_5_or_better(name) -> None:
    result = subprocess.run(["systemd-analyze", "security", "--offline=true", "--no-pager",
                             str(UNITS[name])], capture_output=True, text=True, check=False)
    found = re.search(rf"Overall exposure level for {re.escape(name)}: (\d+\.\d)",
                      result.stdout)
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


def test_the_zenoh_config_loads_in_zenoh() -> None:
    config = json.loads(str(zenoh.Config.from_file(str(ZENOH))))
    assert config["access_control"]["enabled"] is True
    assert config["transport"]["auth"]["usrpwd"]["dictionary_file"].startswith("/etc/busgate/")


class Declared:
    """What the stand-in session declares: a subscriber that never receives, a publisher
    that sends nothing."""

    def __iter__(self):
        return iter(())

    def try_recv(self) -> None:
        return None

    def put(self, *_: object, **__: object) -> None:
        pass

    def undeclare(self) -> None:
        pass

    def declare_matching_listener(self, *_: object) -> Declared:
        """A querier's: it never matches (``matching_status``)."""
        return Declared()

    matching_status = SimpleNamespace(matching=False)


class DeclaringSession:
    """A stand-in for the gateway's zenoh session that notes what it is asked to declare, as
    the access control's message names it (a publisher's messages are puts)."""

    def __init__(self) -> None:
        self.declared: list[tuple[str, str]] = []

    def _noted(self, message: str) -> Callable[..., Declared]:
        def declare(key: str, *_: object, **__: object) -> Declared:
            self.declared.append((message, str(key)))
            return Declared()

        return declare

    def __getattr__(self, name: str) -> Callable[..., Declared]:
        message = {"declare_subscriber": "declare_subscriber", "declare_publisher": "put",
                   "declare_queryable": "declare_queryable"}[name]
        return self._noted(message)

    def liveliness(self) -> SimpleNamespace:
        return SimpleNamespace(declare_subscriber=self._noted("declare_liveliness_subscriber"),
                               declare_token=self._noted("liveliness_token"), get=self.get)

    def get(self, *_: object, **__: object) -> Declared:
        """A get answered by nobody: no declaration (the look for another gateway of the
        name, ``bridge`` rule 7)."""
        return Declared()

    def declare_querier(self, *_: object, **__: object) -> Declared:
        """A querier declares nothing the access control names: its gets are queries."""
        return Declared()


#: What the gateway declares that the access control keeps in on purpose: its watch for
#: another gateway of its name (``bridge`` rule 7). Gateways under it never meet one another
#: (each is a peer its clients connect to), and a gateway hearing gateways' tokens would let
#: any account pass it one.
KEPT_IN = [("declare_liveliness_subscriber", "busgate/gw/alive")]


def test_every_key_the_gateway_declares_is_allowed_out_to_an_operator(monkeypatch) -> None:
    """What the gateway declares (the subscribers and queryables it serves, its publishers,
    its liveliness) must be allowed out by the access control, to an operator at least: a
    key left out is one a secured gateway never hears (a base's twist, the e-stop) or never
    tells (a base's odometry), with no error anywhere."""
    acl = json.loads(str(zenoh.Config.from_file(str(ZENOH))))["access_control"]
    rules = {rule["id"]: rule for rule in acl["rules"]}
    allowed = [rules[r] for p in acl["policies"] if set(p["subjects"]) & {"operator", "anyone"}
               for r in p["rules"]]
    session = DeclaringSession()
    monkeypatch.setattr(bridge_module.zenoh, "open", lambda config: session)
    config = base_config_of([BASE])
    runners = {bus.name: build_bus(bus) for bus in config.buses}  # not started: nothing opened
    bridge = bridge_module.ZenohBridge(config, GatewayApi("gw", runners), runners, deque(),
                                       deque())
    bridge.open(asyncio.new_event_loop())
    keys = {key for _, key in session.declared}
    assert {"busgate/gw/base/*/twist", "busgate/gw/base/base/odom", "busgate/gw/estop/**"} <= keys

    def allows(message: str, key: str) -> bool:
        return any(message in rule["messages"] and "egress" in (rule.get("flows") or ["egress"])
                   and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key))
                           for k in rule["key_exprs"]) for rule in allowed)

    refused = [(message, key) for message, key in session.declared if not allows(message, key)]
    assert refused == KEPT_IN


@pytest.fixture
def secured_gateway(secured_daemon):
    """The module's secured daemon; the sessions a test opens are closed after it."""
    yield secured_daemon
    secured_daemon.close_sessions()


@pytest.fixture
def operator(secured_gateway) -> zenoh.Session:
    return _ready(secured_gateway.connect("operator", "op-secret"))


@pytest.fixture
def viewer(secured_gateway) -> zenoh.Session:
    return _ready(secured_gateway.connect("viewer", "view-secret"))


INFO = "busgate/gw1/info"
LA1 = "busgate/gw1/dev/la1"
ESTOP = la.ControlCommand(1, la.ControlCode.ESTOP)
#: How long a peer turned away waits for an answer that cannot come.
SETTLE_S = 0.5
#: Target positions used once in this module: a frame carrying one came from its test.
FRESH_TARGETS = itertools.count(101, 13)


def _answers(session: zenoh.Session, key: str, payload: str = "", timeout: float = 10.0) -> list:
    replies = session.get(key, payload=payload, timeout=timeout)
    return [json.loads(reply.ok.payload.to_bytes()) for reply in replies if reply.ok]


def _until_answered(session: zenoh.Session, key: str, payload: str = "") -> list:
    deadline = time.monotonic() + 20
    while not (answers := _answers(session, key, payload)):
        assert time.monotonic() < deadline, f"no answer on {key}"
    return answers


def _ready(session: zenoh.Session) -> zenoh.Session:
    """``session`` once the gateway answers it (so the gateway's declarations reached it)."""
    assert _until_answered(session, INFO)[0]["ok"] is True
    return session


def _enable(operator: zenoh.Session) -> None:
    """Power la1 after an earlier test's e-stop (an e-stopped actuator refuses motion), and
    end the follow stream an earlier test's target started (a one-shot target for a device a
    stream follows is refused); ended by a client of its own, whose targets alone the end
    would hold back for a while."""
    for command in ({"op": "enable"}, {"op": "end_follow", "client": "tidy"}):
        reply = _until_answered(operator, f"{LA1}/cmd", json.dumps(command))
        assert reply[0]["ok"] is True, reply


def _frames_since(simulator: SerialSimulator, mark: int) -> list:
    """The frames the actuator received after the first ``mark``, decoded."""
    decoder = la.CommandDecoder()
    for record in simulator.recorder.received()[mark:]:
        decoder.feed(bytes.fromhex(record.wire))
    return list(decoder.events())


def _gateway_had_its_chance(session: zenoh.Session, simulator: SerialSimulator) -> None:
    """Return once whatever ``session`` sent before would be on the actuator's wire had the
    gateway let it through. Zenoh delivers one session's messages to the gateway in order and
    the gateway hands a command to its bus inside the callback, so an answer to a later get
    of ``session`` means the earlier put or get was refused or handed over; three frames the
    simulator received after that answer mean the bus thread, which takes commands and e-stops
    and starts a stream ahead of its polls, has been through its inbox since."""
    assert _until_answered(session, INFO)[0]["ok"] is True
    mark = len(simulator.recorder.received())
    deadline = time.monotonic() + 20
    while len(simulator.recorder.received()) < mark + 3:
        assert time.monotonic() < deadline, "the bus stopped"
        time.sleep(0.01)


def _asked_since(simulator: SerialSimulator, mark: int) -> set[int | str]:
    """What the frames since ``mark`` asked of the actuator: each target, and "estop"."""
    frames = _frames_since(simulator, mark)
    asked: set[int | str] = {"estop"} if ESTOP in frames else set()
    for frame in frames:
        if isinstance(frame, la.MoveCommand | la.FollowCommand):
            asked.add(frame.position_raw)
        elif isinstance(frame, la.GroupMoveCommand | la.GroupFollowCommand):
            asked.update(target.position_raw for target in frame.targets)
    return asked


# -- who gets a session -------------------------------------------------------------------

#: Ways to the gateway's port that must not give a session: credentials missing or wrong over
#: TLS, and the right ones over plain TCP.
TURNED_AWAY = {
    "no credentials": {},
    "wrong password": {"user": "operator", "password": "guess"},
    "plain tcp": {"user": "operator", "password": "op-secret", "scheme": "tcp"},
}


@pytest.mark.parametrize("link", TURNED_AWAY.values(), ids=TURNED_AWAY)
def test_a_client_turned_away_gets_no_session(secured_gateway, link) -> None:
    """A client session cannot exist without its router: zenoh refuses to open it."""
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        secured_gateway.connect(**link)


@pytest.mark.parametrize("link", TURNED_AWAY.values(), ids=TURNED_AWAY)
def test_a_peer_turned_away_opens_alone_and_reaches_nothing(secured_gateway, link) -> None:
    """A peer session opens without anyone (peers may be alone), but no transport to the
    gateway came up: nothing it sends can reach the gateway, nothing answers it. Its
    connection is tried in the background, so a twin that insists on its attempt proves the
    gateway turns it away (instead of a wait that a slow machine could outlast)."""
    peer = secured_gateway.connect(mode="peer", **link)
    with pytest.raises(zenoh.ZError):
        secured_gateway.connect(mode="peer", insist=True, **link)
    assert _answers(peer, INFO, timeout=SETTLE_S) == []
    assert list(peer.info.transports()) == []


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_tls_with_an_account_reaches_the_gateway(secured_gateway, mode) -> None:
    """The counterpart of the two tests above: the same sessions with what they lacked."""
    session = secured_gateway.connect("viewer", "view-secret", mode=mode)
    assert _until_answered(session, INFO)[0]["ok"] is True
    assert len(list(session.info.transports())) == 1


# -- what each account can do -------------------------------------------------------------


def test_operators_command_everyone_reads_telemetry(operator, viewer, wait_for) -> None:
    states = []
    viewer.declare_subscriber("busgate/*/dev/*/state", states.append)
    assert _answers(viewer, INFO)[0]["ok"] is True
    status = json.dumps({"op": "status"})
    reply = _answers(operator, f"{LA1}/cmd", status)
    assert reply[0]["ok"] is True, reply
    assert _answers(viewer, f"{LA1}/cmd", status) == [], "a viewer commanded"
    wait_for(lambda: states)


def test_an_operators_move_is_answered_and_goes_on_the_wire(secured_gateway, operator) -> None:
    _enable(operator)
    target = next(FRESH_TARGETS)
    mark = len(secured_gateway.simulator.recorder.received())
    reply = _answers(operator, f"{LA1}/cmd", json.dumps({"op": "move", "position": target}))
    assert reply[0]["ok"] is True and reply[0]["state"]["target"] == target, reply
    assert la.MoveCommand(1, target) in _frames_since(secured_gateway.simulator, mark)


@dataclass(frozen=True)
class Attempt:
    """One way to move or stop la1; ``payload`` is given a target position used once."""

    how: str  # "put" or "get"
    key: str
    payload: Callable[[int], dict]
    stops: bool = False

    def send(self, session: zenoh.Session, target: int) -> list:
        """Make the attempt; the answers to a get, none for a put."""
        body = json.dumps(self.payload(target))
        if self.how == "get":
            return _answers(session, self.key, body)
        session.put(self.key, body)
        return []

    def asks(self, target: int) -> int | str:
        """What the attempt puts on the wire when it gets through."""
        return "estop" if self.stops else target


def _move(target: int) -> dict:
    return {"op": "move", "position": target}


ATTEMPTS = {
    "put a move": Attempt("put", f"{LA1}/cmd", _move),
    "get a move": Attempt("get", f"{LA1}/cmd", _move),
    "put a follow target": Attempt("put", f"{LA1}/follow", lambda p: {"position": p}),
    "get a group move": Attempt("get", "busgate/gw1/bus/uart0/cmd", lambda p: {
        "op": "group_move", "targets": [{"device": "la1", "position": p}]}),
    "put a device e-stop": Attempt("put", f"{LA1}/cmd", lambda p: {"op": "estop"}, stops=True),
    "put the gateway's e-stop": Attempt("put", "busgate/gw1/estop", lambda p: {}, stops=True),
    "put the fleet's e-stop": Attempt("put", "busgate/*/estop", lambda p: {}, stops=True),
    "get a trajectory": Attempt("get", "busgate/gw1/trajectory", lambda p: {
        "op": "play", "id": f"to-{p}", "devices": ["la1"],
        "points": [{"t_s": 0.04, "positions": [p]}]}),
}


@pytest.mark.parametrize("attempt", ATTEMPTS.values(), ids=ATTEMPTS)
def test_a_viewers_command_never_reaches_the_wire_an_operators_does(
        attempt, secured_gateway, operator, viewer, wait_for) -> None:
    _enable(operator)  # so that nothing but the access control could stop the viewer
    simulator = secured_gateway.simulator
    viewer_target, operator_target = next(FRESH_TARGETS), next(FRESH_TARGETS)
    mark = len(simulator.recorder.received())
    assert attempt.send(viewer, viewer_target) == [], "a viewer was answered"
    _gateway_had_its_chance(viewer, simulator)
    assert attempt.asks(viewer_target) not in _asked_since(simulator, mark), "a viewer's got out"
    attempt.send(operator, operator_target)  # the same attempt shows up when allowed
    wait_for(lambda: attempt.asks(operator_target) in _asked_since(simulator, mark))


def test_every_account_reads_a_trajectorys_feedback(operator, viewer, wait_for) -> None:
    _enable(operator)
    heard: list[dict] = []
    viewer.declare_subscriber("busgate/gw1/trajectory/*/feedback",
                              lambda s: heard.append(json.loads(s.payload.to_bytes())))
    play = {"op": "play", "id": "seen", "devices": ["la1"],
            "points": [{"t_s": 0.3, "positions": [next(FRESH_TARGETS)]}]}
    [reply] = _answers(operator, "busgate/gw1/trajectory", json.dumps(play))
    assert reply["ok"] is True, reply
    wait_for(lambda: any(m.get("result") for m in heard))
    assert any("t_s" in m for m in heard)  # feedback before the result


def test_no_account_passes_fake_telemetry_info_or_liveliness_to_another(
    operator, viewer, wait_for
) -> None:
    """Reading is one-way: only the gateway publishes state, answers info and holds alive
    tokens. A viewer's fake ones never reach the operator, while the gateway's real ones do."""
    states: list[bytes] = []
    operator.declare_subscriber(f"{LA1}/state", lambda s: states.append(s.payload.to_bytes()))
    fake_info = viewer.declare_queryable(
        "busgate/gw9/info", lambda query: query.reply("busgate/gw9/info", b'{"ok":true}'))
    fake_alive = viewer.liveliness().declare_token("busgate/gw9/alive")
    viewer.put(f"{LA1}/state", b'{"forged":true}')
    # The gateway routes the viewer's messages in order: once it answered a later get, it
    # has taken in (or refused) the declarations and the forged state, and a state of its own
    # published after that reaches the operator after anything it forwarded from the viewer.
    assert _until_answered(viewer, INFO)[0]["ok"] is True
    answered = time.time()
    wait_for(lambda: any(json.loads(s).get("ts", 0) > answered for s in states
                         if b"forged" not in s), timeout=20)
    assert not [s for s in states if b"forged" in s], "a viewer's state reached the operator"
    infos = [str(r.ok.key_expr) for r in operator.get("busgate/*/info", timeout=10) if r.ok]
    assert infos == ["busgate/gw1/info"], infos
    alive = [str(r.ok.key_expr) for r in operator.liveliness().get("busgate/*/alive", timeout=10)
             if r.ok]
    assert alive == ["busgate/gw1/alive"], alive
    fake_info.undeclare()
    fake_alive.undeclare()


def test_only_the_operator_resets_the_gateways_estop(
        secured_gateway, operator, viewer, wait_for) -> None:
    """After an e-stop of the enabled la1, a viewer's put on the reset key is refused by the
    access control (no enable goes out), the operator's brings la1 back enabled."""
    _enable(operator)
    simulator = secured_gateway.simulator
    operator.put("busgate/gw1/estop", b"{}")
    wait_for(lambda: ESTOP in _frames_since(simulator, 0))
    mark = len(simulator.recorder.received())
    enable = la.ControlCommand(1, la.ControlCode.ENABLE)
    viewer.put("busgate/gw1/estop/reset", b"{}")
    _gateway_had_its_chance(viewer, simulator)
    assert enable not in _frames_since(simulator, mark), "a viewer reset the e-stop"
    operator.put("busgate/gw1/estop/reset", b"{}")
    wait_for(lambda: enable in _frames_since(simulator, mark))


# -- the ROS 2 face under the same access control (domain 0, node busgate_gw1) --------------
# Last in the module: the face's e-stop is reset, and its hold on la1 left to lapse, by the
# tests themselves, so nothing after them would find la1 stopped or held.

JOINT_STATE = "sensor_msgs/msg/JointState"
TRIGGER = "std_srvs/srv/Trigger"
NODE = "busgate_gw1"
#: The GID and sequence numbers of the tests' ROS publisher and service client.
ROS_GID = bytes(range(rmw_zenoh.GID_SIZE))
ROS_SEQUENCE = itertools.count(1)


def _ros_key(name: str, type_name: str) -> str:
    return rmw_zenoh.data_key(0, name, type_name, "jazzy")


def _ros_attachment() -> bytes:
    return rmw_zenoh.attachment(next(ROS_SEQUENCE), time.time_ns(), ROS_GID)


def _la1_estopped(session: zenoh.Session) -> bool:
    [info] = _until_answered(session, INFO)
    return next(device["state"]["estopped"] for bus in info["buses"]
                for device in bus["devices"] if device["name"] == "la1")


def test_every_account_reads_the_ros_joint_states(operator, viewer, wait_for) -> None:
    heard: dict[str, list] = {"operator": [], "viewer": []}
    for session, got in ((operator, heard["operator"]), (viewer, heard["viewer"])):
        session.declare_subscriber("0/robot_joint_states/**", lambda s, got=got: got.append((
            messages.decode(JOINT_STATE, s.payload.to_bytes()),
            rmw_zenoh.read_attachment(s.attachment.to_bytes() if s.attachment else None))))
    wait_for(lambda: all(got for got in heard.values()))
    for got in heard.values():
        state, attachment = got[0]
        assert state is not None and "la1" in state["name"], state
        assert attachment is not None  # rmw_zenoh's, or a ROS subscriber would drop it


def test_a_viewers_ros_estop_call_is_unanswered_an_operators_stops_every_bus(
        secured_gateway, operator, viewer, wait_for) -> None:
    """The e-stop service stops whatever its request looks like: the access control alone
    keeps a viewer from it. The operator's call is answered once every bus stopped; the
    operator's reset brings la1 back enabled, as the test found it."""
    _enable(operator)
    simulator = secured_gateway.simulator
    key = _ros_key(f"/{NODE}/estop", TRIGGER)
    request = messages.encode(f"{TRIGGER}_Request", {})
    mark = len(simulator.recorder.received())
    assert list(viewer.get(key, payload=request, attachment=_ros_attachment(),
                           timeout=SETTLE_S)) == [], "a viewer was answered"
    _gateway_had_its_chance(viewer, simulator)
    assert "estop" not in _asked_since(simulator, mark), "a viewer's e-stop got out"
    [reply] = operator.get(key, payload=request, attachment=_ros_attachment(), timeout=10)
    assert reply.ok is not None, reply.err.payload.to_string()
    response = messages.decode(f"{TRIGGER}_Response", reply.ok.payload.to_bytes())
    assert response is not None and response["success"] is True, response
    wait_for(lambda: "estop" in _asked_since(simulator, mark))
    mark = len(simulator.recorder.received())
    operator.put("busgate/gw1/estop/reset", b"{}")
    wait_for(lambda: la.ControlCommand(1, la.ControlCode.ENABLE) in _frames_since(simulator, mark))
    wait_for(lambda: not _la1_estopped(operator))


def test_a_viewers_ros_joint_command_never_reaches_the_wire_an_operators_does(
        secured_gateway, operator, viewer, wait_for) -> None:
    """la1 has no joint table: in ROS it is the raw joint ``la1``, a position in counts. The
    operator's command makes the face hold la1 (as any ROS controller's) until the hold
    lapses, which the test waits for."""
    _enable(operator)  # so that nothing but the access control could stop the viewer
    simulator = secured_gateway.simulator
    key = _ros_key("/robot_joint_commands", JOINT_STATE)
    viewer_target, operator_target = next(FRESH_TARGETS), next(FRESH_TARGETS)

    def command(target: int) -> bytes:
        return messages.encode(JOINT_STATE, {"name": ["la1"], "position": [float(target)]})

    mark = len(simulator.recorder.received())
    viewer.put(key, command(viewer_target), attachment=_ros_attachment())
    _gateway_had_its_chance(viewer, simulator)
    assert viewer_target not in _asked_since(simulator, mark), "a viewer's command got out"
    operator.put(key, command(operator_target), attachment=_ros_attachment())
    wait_for(lambda: operator_target in _asked_since(simulator, mark))
    enable = json.dumps({"op": "enable"})  # refused ``claimed`` while the face holds la1
    wait_for(lambda: _answers(operator, f"{LA1}/cmd", enable)[0]["ok"], timeout=10)
