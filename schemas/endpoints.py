"""zenoh endpoints as busgate takes them (``tcp/127.0.0.1:7447``): what their port may be,
and whether one listens beyond this host. zenoh parses an endpoint only when a session
opens, and takes a port of 70000 then, to fail later as "unable to connect"; the config is
validated offline, without zenoh (``busgate check-config``), so the port is checked here, for
the config and for every session (``zenoh_session``) alike.

Rules of this file:

1. An endpoint of a network protocol (``tcp``, ``udp``, ``tls``, ``quic``, ``ws``) ends with
   ``host:port`` (then, maybe, zenoh's ``?`` metadata or ``#`` configuration), its port a
   number from 1 to 65535, its host an IPv6 address in brackets where it has a colon (one
   bracket alone, ``tcp/[::1:7447``, was taken offline and failed the session's lookup).
   Port 0 is refused to a listener too: zenoh would pick a port and tell nobody, so no
   client could be told where to connect.
2. A ``unixsock-stream`` endpoint has a path, no port; it is reachable from this host only.
3. A listener is reachable from this host only when its host is a loopback address
   (``127.0.0.0/8``, ``::1``) or ``localhost``.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Callable, Sequence
from typing import Annotated, Literal, get_args

from pydantic import AfterValidator, Field

#: The modes a zenoh session may have: a gateway's (config) and the router's.
ZenohMode = Literal["peer", "client", "router"]
ZENOH_MODES: tuple[str, ...] = get_args(ZenohMode)
#: The protocols whose endpoints end with ``host:port`` (rule 1).
NETWORK_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
#: Every protocol an endpoint may have: those, and a Unix socket's (rule 2).
PROTOCOLS = (*NETWORK_PROTOCOLS, "unixsock-stream")
PATTERN = rf"^({'|'.join(PROTOCOLS)})/\S*$"
#: What an endpoint is, as a refusal of one that is none says it.
ENDPOINT_FORM = f"protocol/address, its protocol one of {', '.join(PROTOCOLS)}"
#: Those over TCP: a listener on one takes a TCP port.
TCP_PROTOCOLS = ("tcp", "tls", "ws")
_ADDRESS = re.compile(
    rf"^(?P<protocol>{'|'.join(NETWORK_PROTOCOLS)})/(?P<host>.*):(?P<port>[^:]*)$"
)
PORTS = (1, 65535)


def port_problem(endpoint: str, *, listening: bool = False) -> str | None:
    """What is wrong with the port of ``endpoint`` (rule 1), ``None`` when nothing is (or it
    is of no protocol of ``NETWORK_PROTOCOLS``: zenoh judges those)."""
    address = _address(endpoint)
    if address is None:
        if endpoint.startswith(tuple(f"{name}/" for name in NETWORK_PROTOCOLS)):
            return "it names no port: write host:port (tcp/127.0.0.1:7447)"
        return None
    port = address["port"]
    number = int(port) if port.isascii() and port.isdigit() else None
    if listening and number == 0:
        return "port 0 is one zenoh picks and tells nobody: name the port clients connect to"
    if number is None or not PORTS[0] <= number <= PORTS[1]:  # tcp/[::1] too: port "1]"
        return f"port {port!r} is no port: from {PORTS[0]} to {PORTS[1]}"
    host = address["host"]
    if host.startswith("[") != host.endswith("]") or (":" in host and not host.startswith("[")):
        return f"host {host!r} is no host: an IPv6 address goes in brackets (tcp/[::1]:7447)"
    return None


def host_of(endpoint: str) -> str | None:
    """The host an endpoint of ``NETWORK_PROTOCOLS`` names (an IPv6 address without its
    brackets); ``None`` for any other.

    >>> host_of("tcp/[::1]:7447"), host_of("tls/gw.local:7447"), host_of("unixsock-stream//x")
    ('::1', 'gw.local', None)
    """
    address = _address(endpoint)
    return None if address is None else address["host"].strip("[]")


def port_of(endpoint: str) -> int | None:
    """The port an endpoint of ``NETWORK_PROTOCOLS`` names; ``None`` for any other, or one
    that is no number.

    >>> port_of("tcp/[::1]:7447"), port_of("udp/h:x"), port_of("unixsock-stream//x")
    (7447, None, None)
    """
    address = _address(endpoint)
    port = None if address is None else address["port"]
    return int(port) if port is not None and port.isascii() and port.isdigit() else None


def settings_of(endpoint: str) -> dict[str, str]:
    """zenoh's configuration of an endpoint, after its ``#``: ``key=value`` pairs split by ``;``.

    >>> settings_of("tcp/127.0.0.1:7447#iface=eth0;so_sndbuf=65000"), settings_of("tcp/h:1")
    ({'iface': 'eth0', 'so_sndbuf': '65000'}, {})
    """
    pairs = endpoint.partition("#")[2].split(";")
    return dict(pair.partition("=")[::2] for pair in pairs if pair)


def beyond_this_host(endpoint: str) -> bool:
    """Whether a listener on ``endpoint`` can be reached from other hosts (rule 3)."""
    address = _address(endpoint)
    if address is None:
        return False  # a Unix socket (rule 2)
    host = address["host"].strip("[]")
    if host == "localhost":
        return False
    try:
        return not ipaddress.ip_address(host).is_loopback
    except ValueError:
        return True  # a host name: whatever it resolves to


def exposure_warnings(listen: list[str], config_file: str | None) -> list[str]:
    """Each listener of a gateway's config (``zenoh.listen``) that other hosts can reach
    with no zenoh config file to give it TLS, passwords or access control (a file of the
    operator's own is trusted to)."""
    if config_file is not None:
        return []
    return [
        f"zenoh.listen[{index}]: {endpoint} can be reached from other hosts, and no "
        "zenoh.config_file gives it TLS, passwords or access control: whoever reaches it "
        "moves every device (docs/running.md#threat-model-who-can-move-what)"
        for index, endpoint in enumerate(listen)
        if beyond_this_host(endpoint)
    ]


def takes_tcp_port(endpoint: str, host: str, port: int) -> bool:
    """Whether a listener on ``endpoint`` would take the TCP port ``host:port`` (its own, or
    every address's, or ``host`` is every address)."""
    address = _address(endpoint)
    if address is None or address["protocol"] not in TCP_PROTOCOLS:
        return False
    if address["port"] != str(port):
        return False
    hosts = {host.strip("[]"), address["host"].strip("[]")}
    if len(hosts) == 1 or "::" in hosts:  # the IPv6 wildcard takes IPv4's too (dual stack)
        return True
    return "0.0.0.0" in hosts and not any(":" in named for named in hosts)  # IPv4's alone


def share_a_tcp_port(first: str, second: str) -> bool:
    """Whether listeners on ``first`` and ``second`` would take one TCP port (the same host,
    or one of them every address's): the second to bind finds it in use.

    >>> share_a_tcp_port("tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447")
    True
    >>> share_a_tcp_port("tcp/127.0.0.1:7447", "udp/127.0.0.1:7447")
    False
    >>> share_a_tcp_port("tcp/0.0.0.0:7447", "tcp/[::1]:7447")  # one family each: both bind
    False
    """
    address = _address(second)
    if address is None or address["protocol"] not in TCP_PROTOCOLS:
        return False
    port = address["port"]
    return port.isdecimal() and takes_tcp_port(first, address["host"], int(port))


def is_endpoint(endpoint: str) -> bool:
    """Whether ``endpoint`` is of a protocol busgate knows, ``protocol/address`` (rule 1)."""
    return re.match(PATTERN, endpoint) is not None


def clash_at(listen: Sequence[str], index: int) -> tuple[str, str] | None:
    """What keeps ``listen[index]`` from listening beside the others, as the two that clash:
    itself given twice (anywhere in ``listen``), or one before it whose TCP port it would take
    (``share_a_tcp_port``): zenoh would find it in use, by the same gateway or router.

    >>> clash_at(["tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447"], 1)
    ('tcp/0.0.0.0:7447', 'tcp/127.0.0.1:7447')
    """
    endpoint = listen[index]
    if listen.count(endpoint) > 1:
        return endpoint, endpoint
    other = next((o for o in listen[:index] if share_a_tcp_port(o, endpoint)), None)
    return None if other is None else (other, endpoint)


def _address(endpoint: str) -> re.Match[str] | None:
    """``endpoint``'s protocol, host and port, without zenoh's metadata and configuration."""
    return _ADDRESS.match(re.split(r"[?#]", endpoint, maxsplit=1)[0])


def _refusing(*, listening: bool) -> Callable[[str], str]:
    """A validator that refuses an endpoint of a protocol busgate does not know, or whose
    port is wrong (rule 1)."""

    def check(endpoint: str) -> str:
        if not is_endpoint(endpoint):
            raise ValueError(f"an endpoint is {ENDPOINT_FORM} (tcp/127.0.0.1:7447)")
        problem = port_problem(endpoint, listening=listening)
        if problem is not None:
            raise ValueError(problem)
        return endpoint

    return check


#: The published JSON schema keeps the pattern (an editor checks what it can); the check
#: itself is the validator's, with a refusal in words.
_IN_SCHEMA = Field(json_schema_extra={"pattern": PATTERN})
#: An endpoint in a config: its protocol one busgate knows, its port a port (rule 1).
Endpoint = Annotated[str, _IN_SCHEMA, AfterValidator(_refusing(listening=False))]
#: An endpoint a config listens on: its port named (rule 1).
ListenEndpoint = Annotated[str, _IN_SCHEMA, AfterValidator(_refusing(listening=True))]
