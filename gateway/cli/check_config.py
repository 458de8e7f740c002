"""``busgate check-config FILE``: validate a config and print each bus's budget.

Rules of this file: it checks without touching hardware. Whatever ``busgate run`` would refuse
(``load_config`` raises ``ConfigError``, one key path per line) is an error: printed on stderr,
exit status 1. What only this host or the load decides — a port that does not exist here, is
locked by another process, is no serial port, or a CAN interface python-can does not have here
(``busgate run`` refuses those three), a port this user may not read and write, a bus whose
streams cannot all fit, a flight recorder's folder this user cannot write, a zenoh config file
missing or that zenoh cannot parse, a listener other hosts reach with no zenoh config file to
keep them out, more bus workers than the cores this host gives the gateway, a CAN bus's option
that python-can's bus for its interface names no parameter for (passed on all the same; not
told when that bus cannot be loaded here) — is a warning, as
is a key that is taken but ignored (``ignored_keys``, which ``busgate run`` logs: a joint
table's, a heartbeat interval off CAN)
and a gateway that listens nowhere, connects nowhere and scouts for nobody (valid: a zenoh
config file may give it endpoints; else no client reaches it): printed with the budget. Exit
status 0 (a zenoh listen port another socket holds now is a warning too: the holder may be
the gateway being checked), unless a warning is one ``busgate run`` on this host refuses to
start with (a port
that is no serial port, a CAN interface python-can does not have here, a recorder's folder
it cannot write, a zenoh config file or endpoint it cannot use, a listener zenoh cannot listen
on here — a tls/ or quic/ one given no private key or certificate, a host that does not
resolve, a network interface this host has not, a Unix socket's path too long for one or in a
folder that does not exist — or a metrics host that does not resolve): then 2, with a last line on
stderr saying so, so that a deployment script stops where the service would not start. A
locked port stays a warning, exit 0: its holder may be the very gateway being checked.
"""

from __future__ import annotations

import argparse
import errno
import os
import socket
import sys
from pathlib import Path

from busgate.errors import ConfigError
from busgate.gateway.bus.can_options import unknown_interface, unnamed_options
from busgate.gateway.bus.port_access import NOT_A_DEVICE, missing, port_problem
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.recording.flight import folder_problem
from busgate.gateway.service.budget import bus_budget
from busgate.gateway.service.placement import placement, too_many
from busgate.schemas.config import CanBus, Config, SerialBus, ignored_keys, load_config
from busgate.schemas.endpoints import exposure_warnings, host_of, port_of, settings_of

#: The longest path a Unix socket takes, in bytes (``sun_path``'s 108, with its NUL).
UNIX_PATH_MAX = 107
#: The listeners' protocols over UDP (``_in_use`` asks for a datagram socket); the others TCP.
DATAGRAM_PROTOCOLS = ("udp", "quic")


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    check = subparsers.add_parser(
        "check-config",
        description="Validate a gateway config without touching hardware, and print per bus "
        "the wire time its polling and follow streams take and the share of the bus they "
        "reserve. Exit status 1 when the config is invalid, 2 when it is valid but busgate "
        "run on this host would refuse to start with it (a warning says why).",
    )
    check.add_argument("file", type=named_path, help="the gateway's TOML config file")
    check.set_defaults(handler=check_config)


def check_config(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        for line in str(exc).splitlines():
            print(f"error: {line}", file=sys.stderr)
        return 1
    print(f"{args.file}: valid; {_overview(config)}")
    groups = placement(config)
    print(_workers(config, groups))
    if (crowded := too_many(len(groups))) is not None:
        print(f"warning: {crowded}")
    refusals = 0  # the warnings busgate run refuses to start with, on this host
    if config.recorder is not None and (problem := folder_problem(Path(config.recorder.dir))):
        refusals += 1
        print(
            f"warning: recorder.dir: {problem}; busgate run refuses to start so (run this as "
            "the service user to check its access; the systemd unit makes the default dir)"
        )
    refused, warned = zenoh_warnings(config)
    if config.metrics is not None and (
        unresolved := _unresolved(config.metrics.listen.rpartition(":")[0])
    ):
        refused.append(
            f"metrics.listen: {config.metrics.listen}: {unresolved}; busgate run refuses to "
            "start so"
        )
    refusals += len(refused)
    for problem in [*refused, *warned, *ignored_keys(config)]:
        print(f"warning: {problem}")
    for index, bus in enumerate(config.buses):
        budget = bus_budget(bus)
        print(budget.summary())
        refused, warned = host_warnings(f"buses[{index}]", bus)
        refusals += len(refused)
        problems = [
            *refused,
            *warned,
            *_option_warnings(f"buses[{index}]", bus),
            *(f"buses[{index}]: {text}" for text in budget.warnings()),
            *(
                f"buses[{index}].devices[{at}]: {device.name} has no joint table: it is a joint "
                "in raw units limited only by the device's own range (docs/joints.md)"
                for at, device in enumerate(bus.devices)
                if device.joint is None
            ),
        ]
        for problem in problems:
            print(f"warning: {problem}")
    if refusals:
        print(
            f"{args.file}: valid, but busgate run on this host refuses to start with it "
            f"({refusals} of the warnings above)",
            file=sys.stderr,
        )
        return 2
    return 0


def zenoh_warnings(config: Config) -> tuple[list[str], list[str]]:
    """What ``busgate run`` refuses to start with: a zenoh config file this host has not, or
    that is none, or endpoints the session cannot be made of on this host (a Unix socket's
    path that is a file), or where zenoh cannot listen here (``_session_refusals``); and
    what it starts with all the same: each listener other hosts
    can reach with nothing but a file of the operator's own (TLS, passwords, access control)
    to keep them from moving the devices, a gateway that listens and connects nowhere."""
    zenoh_file, refused, warned = config.zenoh.config_file, [], []
    file_refusal = None
    if zenoh_file is not None:
        from busgate.schemas.zenoh_session import config_file_refusal  # loads zenoh: only here

        file_refusal = config_file_refusal(zenoh_file)
    refusal, listeners, in_use = (
        (file_refusal, [], []) if file_refusal else _session_refusals(config)
    )
    if refusal:
        where = "zenoh" if zenoh_file is None else f"zenoh.config_file: {zenoh_file}"
        refused.append(f"{where}: {refusal}; busgate run refuses to start so")
    elif zenoh_file is None and not (
        config.zenoh.listen or config.zenoh.connect or config.zenoh.multicast_scouting
    ):
        from busgate.schemas.zenoh_session import NOBODY_REACHES

        warned.append(f"zenoh: {NOBODY_REACHES}")
    exposed = exposure_warnings(config.zenoh.listen, zenoh_file)
    return refused + listeners, warned + in_use + exposed


def _session_refusals(config: Config) -> tuple[str | None, list[str], list[str]]:
    """Why the zenoh session could not be made of the config file and the endpoints (an
    endpoint of a protocol the file's links leave out), ``None`` when it can; and, made once,
    each endpoint it would listen on (``listen``, or its zenoh config file's) where zenoh
    would refuse to listen on this host (``_listener_problem``), and each in use now."""
    from busgate.schemas.zenoh_session import (  # loads zenoh: only here
        endpoints_of,
        gateway_session_config,
        tls_listen_missing,
    )

    try:
        session = gateway_session_config(config.zenoh)
    except ValueError as exc:
        return str(exc), [], []
    refused, in_use = [], []
    for index, endpoint in enumerate(endpoints_of(session, "listen", config.zenoh.mode)):
        where = (
            f"zenoh.listen[{index}]"
            if config.zenoh.listen
            else f"zenoh.config_file: {config.zenoh.config_file}: listen endpoint {index}"
        )
        if problem := _listener_problem(endpoint, tls_listen_missing(session, endpoint)):
            refused.append(
                f"{where}: cannot listen on {endpoint}: {problem}; busgate run refuses to start so"
            )
        elif _in_use(endpoint):
            in_use.append(
                f"{where}: {endpoint} is in use on this host now (another busgate demo or "
                "run, or this gateway itself?): busgate run refuses to start while it is"
            )
    return None, refused, in_use


def _in_use(endpoint: str) -> bool:
    """Whether a socket of another process holds ``endpoint``'s port here now, as a locked
    serial port is told: a warning, its holder may be the very gateway being checked (an
    audit: check-config passed a port ``busgate run`` then refused)."""
    host, port = host_of(endpoint), port_of(endpoint)
    if host is None or not port:
        return False
    protocol = endpoint.partition("/")[0]
    kind = socket.SOCK_DGRAM if protocol in DATAGRAM_PROTOCOLS else socket.SOCK_STREAM
    try:
        found = socket.getaddrinfo(host, port, type=kind)
    except (OSError, UnicodeError):  # told by ``_listener_problem``
        return False
    for family, sort, proto, _, address in found:
        try:
            with socket.socket(family, sort, proto) as probe:  # IPv6 may be off: EAFNOSUPPORT
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as zenoh's
                probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return True
    return False


def _listener_problem(endpoint: str, tls_missing: list[str]) -> str | None:
    """Why zenoh could not listen on ``endpoint`` here: a tls/ or quic/ listener given no
    private key or certificate (``tls_missing``: ``tls_listen_missing``), a host that does not
    resolve, a network interface (``#iface=``) this host has not, a Unix socket's path longer
    than one takes or in a folder that does not exist; ``None`` when none of those."""
    from busgate.schemas.zenoh_session import unix_socket_path

    if tls_missing:
        return (
            f"a {endpoint.partition('/')[0]} listener needs a private key and a certificate, "
            f"and it has no {' and no '.join(tls_missing)}: set them in a zenoh config file "
            "(docs/running.md#access-control-passwords-and-tls)"
        )
    if (path := unix_socket_path(endpoint)) is not None:
        if len(os.fsencode(path)) > UNIX_PATH_MAX:
            return f"a Unix socket's path is at most {UNIX_PATH_MAX} bytes: name a shorter one"
        if not os.path.isdir(folder := os.path.dirname(path) or "."):
            return f"its folder {folder} does not exist"
    host = host_of(endpoint)
    if host is not None and (unresolved := _unresolved(host)):
        return unresolved
    if (iface := settings_of(endpoint).get("iface")) is not None:
        try:
            socket.if_nametoindex(iface)
        except OSError:
            return f"this host has no network interface {iface!r} (iface)"
    return None


def _unresolved(host: str) -> str | None:
    """Why ``host`` does not resolve here, ``None`` when it does: only the resolver is asked
    (``.invalid`` names never resolve)."""
    try:
        socket.getaddrinfo(host, None)
    except socket.gaierror as exc:
        return f"its host {host} does not resolve here ({exc.strerror})"
    except UnicodeError:  # a label over 63 characters: the resolver is never asked
        return f"its host {host} is no host name"
    return None


def _option_warnings(path: str, bus: SerialBus | CanBus) -> list[str]:
    """Each of a CAN bus's ``options`` that python-can's bus for its interface names no
    parameter for (``unnamed_options``): passed on, and most likely misspelt."""
    if not isinstance(bus, CanBus):
        return []
    return [
        f"{path}.options.{key}: python-can's {bus.interface} bus names no such parameter: "
        "check its spelling (it is passed on all the same)"
        for key in unnamed_options(bus.interface, bus.options.arguments())
    ]


def _overview(config: Config) -> str:
    devices = sum(len(bus.devices) for bus in config.buses)
    metrics = f"metrics on {config.metrics.listen}" if config.metrics else "no metrics endpoint"
    recorder = (
        f"flight recorder ({config.recorder.seconds:g} s) into {config.recorder.dir}"
        if config.recorder
        else "no flight recorder"
    )
    bases = ", ".join(f"base {b.name} (wheels {b.left}, {b.right})" for b in config.bases)
    ros2 = config.ros2
    face = (
        f"ROS 2 node {ros2.node_of(config.gateway.name)} in domain {ros2.domain_id} ({ros2.distro})"
        if ros2
        else "no ROS 2 face"
    )
    return (
        f"gateway {config.gateway.name}, {len(config.buses)} bus(es), {devices} device(s), "
        f"{bases or 'no base'}, {face}, {metrics}, {recorder}"
    )


def _workers(config: Config, groups: list[list[str]]) -> str:
    """Where ``busgate run`` would run each bus on this host: in the workers ``groups``
    (``placement``), or in the gateway's process."""
    if not groups:
        return "workers on this host: none, every bus in the gateway's process"
    split = "; ".join(f"{index}: {', '.join(group)}" for index, group in enumerate(groups))
    placed = {name for group in groups for name in group}
    stay = [bus.name for bus in config.buses if bus.name not in placed]
    return f"workers on this host: {split}" + (
        f"; in the gateway's process: {', '.join(stay)}" if stay else ""
    )


def host_warnings(path: str, bus: SerialBus | CanBus) -> tuple[list[str], list[str]]:
    """What this host would stand in the way of the bus's port or CAN interface, as what
    ``busgate run`` would refuse to start with (a port that is no device file, an interface
    python-can does not have here) and what it would not, or may not: missing (the gateway
    would start and retry until it appears), locked by another process (refused, unless the
    holder is the gateway being checked, and restarted), or not readable and writable by
    this user (run it as the service user to check that user's access)."""
    if isinstance(bus, CanBus) and (unknown := unknown_interface(bus.interface)):
        return [f"{path}.interface: {unknown}; busgate run refuses to start so"], []
    if bus.device_key is not None:
        key, port = bus.device_key
        problem = port_problem(port)
        if problem is None:
            return [], []
        if problem.kind == NOT_A_DEVICE:  # locked is a warning: its holder may be the very
            # gateway being checked, whose restart frees it
            return [f"{path}.{key}: {problem.message}; busgate run refuses to start so"], []
        return [], [f"{path}.{key}: {problem.message}"]
    if bus.interface == "socketcan" and not (Path("/sys/class/net") / bus.channel).exists():
        return [], [f"{path}.channel: {missing(bus.channel)}"]
    return [], []
