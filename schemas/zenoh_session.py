"""Building a ``zenoh.Config`` from busgate's few zenoh settings.

The daemon's session (``gateway/api/bridge.py``) and every client's (``busgate.client``)
are built here, so that a gateway and a client read the same settings the same way; it lives
in the data layer below both (a room of its own would be one module), so neither imports the
other for it. The one module of the schemas that imports ``zenoh``, and only when it is
imported itself (``busgate.schemas`` does not import it): the command line's offline commands
never load zenoh.

Rules: a full zenoh config file (ACL, TLS, auth …) is the base and busgate's settings are laid
over it. ``mode`` and multicast scouting are always set (multicast off unless asked for: a
service talks to the endpoints it is given, never to whoever answers on the LAN), and so is
shared memory, off: busgate's messages are small, and with it on a session maps the segment
(16 MB) of every peer on the host that sends it a large payload, and keeps it (a few local
clients grew a gateway by hundreds of MB, payloads it refused included). ``listen``
and ``connect`` are set when given, so endpoints written in the file survive an empty list;
with neither ``listen`` nor a file, a session listens nowhere (zenoh's default would be every
interface, with no authentication): it reaches others only through ``connect``. A client's
own settings (its lease, a user name and password, the CA of a TLS endpoint) are laid on top
only when given.
"""

from __future__ import annotations

import errno
import json
import os
import re
import socket
import stat
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import zenoh

from busgate.schemas.endpoints import ZENOH_MODES, port_problem, settings_of

if TYPE_CHECKING:
    from busgate.schemas.config import ZenohSection

MODES = ZENOH_MODES
#: The largest zenoh config file or CA certificate taken: each is a few KiB, and zenoh reads
#: whatever it is given whole (``/dev/zero`` without end).
MAX_FILE_BYTES = 1024 * 1024
#: The protocols whose links are TLS's (a CA certificate is theirs).
TLS_PROTOCOLS = ("tls/", "quic/")


#: How long a check for live gateways waits for their liveliness tokens and ``info`` answers:
#: ``busgate replay``'s for its ``--prefix``, a gateway's for its own name before it declares
#: anything (``gateway.api.bridge`` rule 7). A router or a peer answers at once: the wait is
#: only for one that never does.
LIVE_WAIT_S = 1.0

#: What zenoh's refusal to open a session says when no endpoint of its ``connect`` could be
#: reached (nobody listening, a name that does not resolve, a peer that never answered).
UNREACHED = "Unable to connect to any of"

#: What a gateway that listens on no endpoint, connects to none and scouts for no peer is
#: told (its config is valid: a zenoh config file may add endpoints).
NOBODY_REACHES = (
    "the gateway listens on no endpoint and connects to none: no client can reach it (give "
    '[zenoh] listen = ["tcp/127.0.0.1:7447"], or connect to a router)'
)

#: How long a service's stop waits for its session's close (``close_within``): zenoh's close
#: waits for a connect under way, to an endpoint that took the connection and never answers
#: up to zenoh's open timeout (10 s), and systemd's stop gives a service 10 s in all
#: (``TimeoutStopSec``) before it kills it and calls the stop a failure.
CLOSE_WAIT_S = 1.0

#: The largest message a gateway's session takes in, in bytes: twice the largest payload any
#: of its keys takes (a trajectory, 1 MiB; the ROS 2 face's trajectory topic, 1 MiB of CDR).
#: Zenoh's own bound is 1 GiB: the messages waiting for a key's thread (``gateway.api.intake``)
#: are bounded by this, not by what the key later refuses.
MAX_RECEIVED = 2 * 1024 * 1024


def session_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    config_file: str | Path | None = None,
    lease_s: float | None = None,
    username: str | None = None,
    password: str | None = None,
    ca: str | Path | None = None,
) -> zenoh.Config:
    """A zenoh config: ``config_file`` (if any) underneath, the given settings on top.

    Raises ``ValueError`` for an unknown mode, a ``config_file`` that is no file, or a Unix
    socket endpoint it would take from someone (``check_unix_listeners``); zenoh itself
    rejects a malformed file or endpoint.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, not {mode!r}")
    try:
        config = _parsed(config_file) if config_file else zenoh.Config()
    except ValueError as exc:  # not "os error 2"
        raise ValueError(f"the zenoh config file {config_file}: {exc}") from exc
    for endpoints, listening in ((listen, True), (connect, False)):
        for endpoint in endpoints:
            if problem := endpoint_problem(endpoint, listening=listening):
                raise ValueError(f"zenoh endpoint {endpoint!r}: {problem}")
            if listening and list(listen).count(endpoint) > 1:  # else "in use", by itself
                raise ValueError(f"zenoh endpoint {endpoint!r} is given twice")
    _check_protocols(config, [*listen, *connect])
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    config.insert_json5("transport/shared_memory/enabled", "false")
    if listen or not config_file:  # zenoh's own default listens on every interface
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if lease_s is not None:  # what this session announces: a peer that hears nothing from it
        # for that long drops it (its liveliness tokens with it); zenoh's default is 10 s
        config.insert_json5("transport/link/tx/lease", json.dumps(round(lease_s * 1000)))
    if username is not None or password is not None:
        credentials = {"user": username or "", "password": password or ""}
        config.insert_json5("transport/auth/usrpwd", json.dumps(credentials))
    if ca is not None:
        if problem := file_problem(ca, "a CA certificate"):
            raise ValueError(f"the CA certificate {ca}: {problem}")
        config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
        _check_tls_endpoints(config, mode)
    check_unix_listeners(endpoints_of(config, "listen", mode))
    return config


def close_within(session: zenoh.Session, seconds: float = CLOSE_WAIT_S) -> bool:
    """Close ``session`` on a daemon thread of its own, waiting ``seconds`` at most: whether
    it closed. A close that outlasts the wait ends with the process, which goes on to its end
    (the devices were stopped before; nothing of the session is waited for after it)."""
    closing = threading.Thread(target=session.close, name="zenoh-close", daemon=True)
    closing.start()
    closing.join(seconds)
    return not closing.is_alive()


def endpoint_problem(endpoint: str, *, listening: bool = False) -> str | None:
    """What is wrong with ``endpoint`` (its port: ``endpoints``; else what zenoh says when
    it parses it), ``None`` when nothing is."""
    if problem := port_problem(endpoint, listening=listening):
        return problem
    try:
        zenoh.Config().insert_json5("connect/endpoints", json.dumps([endpoint]))
    except zenoh.ZError as exc:
        return clean(zenoh_reason(exc))
    return None


def file_problem(path: str | Path, what: str) -> str | None:
    """Why ``path`` cannot be read as ``what`` here (``no such file``, ``not a file``, over
    ``MAX_FILE_BYTES``: zenoh would read whatever it is whole); ``None`` when it can."""
    path = Path(path)
    if not path.is_file():
        return "not a file" if path.exists() else "no such file"
    if path.stat().st_size > MAX_FILE_BYTES:
        return f"over {MAX_FILE_BYTES // 1024 // 1024} MiB: not {what}"
    return None


def config_file_refusal(config_file: str | Path) -> str | None:
    """Why ``config_file`` is no zenoh config (``_parsed``); ``None`` when it is one."""
    try:
        _parsed(config_file)
    except ValueError as exc:
        return str(exc)
    return None


def gateway_session_config(section: ZenohSection) -> zenoh.Config:
    """The session config of a gateway's ``[zenoh]`` table: the daemon's, and what
    ``check-config`` checks the endpoints against. A message larger than ``MAX_RECEIVED``
    is dropped by zenoh before the gateway holds it, whatever a config file says."""
    config = session_config(
        mode=section.mode,
        listen=section.listen,
        connect=section.connect,
        multicast_scouting=section.multicast_scouting,
        config_file=section.config_file,
    )
    config.insert_json5("transport/link/rx/max_message_size", json.dumps(MAX_RECEIVED))
    return config


def _check_protocols(config: zenoh.Config, endpoints: Sequence[str]) -> None:
    """``ValueError`` for an endpoint of a protocol the config file's links leave out
    (``transport/link/protocols``: ``["tls"]`` in ``deploy/zenoh/busgate.json5``), which
    zenoh would refuse only when the session opens, as "Unsupported protocol"."""
    allowed = json.loads(config.get_json("transport/link/protocols"))
    if not allowed:
        return
    for endpoint in endpoints:
        if endpoint.partition("/")[0] not in allowed:
            raise ValueError(
                f"zenoh endpoint {endpoint!r}: the zenoh config file allows only "
                f"{', '.join(allowed)} links (transport/link/protocols); give a "
                f"{allowed[0]}/ endpoint, or leave listen out to listen where the file says"
            )


def _parsed(config_file: str | Path) -> zenoh.Config:
    """``config_file`` as zenoh reads it; ``ValueError`` saying why it is none
    (``file_problem``, or where zenoh's parser stopped and why)."""
    if problem := file_problem(config_file, "a zenoh config"):
        raise ValueError(problem)
    try:
        return zenoh.Config.from_file(str(config_file))
    except zenoh.ZError as exc:
        raise ValueError(config_file_reason(exc)) from exc


def _check_tls_endpoints(config: zenoh.Config, mode: str) -> None:
    """A CA certificate is for TLS (``tls/``, ``quic/``): refused when no endpoint of the
    session is one, where the link would be in the clear while its user thinks otherwise."""
    endpoints = [*endpoints_of(config, "listen", mode), *endpoints_of(config, "connect", mode)]
    if not any(str(endpoint).startswith(TLS_PROTOCOLS) for endpoint in endpoints):
        where = ", ".join(map(str, endpoints)) or "none"
        raise ValueError(
            f"a CA certificate is for tls/ and quic/ endpoints; this session's are {where}: "
            f"in the clear"
        )


def tls_listen_missing(config: zenoh.Config, endpoint: str) -> list[str]:
    """What a listener on ``endpoint`` of a TLS protocol lacks of a private key and a
    certificate, without which zenoh refuses the session ("Missing TLS private key"): each
    key of the zenoh config (``transport/link/tls/…``) given neither there (as a file or in
    base64) nor in the endpoint's configuration (``#listen_private_key_file=…``); none for an
    endpoint of another protocol."""
    if not endpoint.startswith(TLS_PROTOCOLS):
        return []
    settings = settings_of(endpoint)
    return [
        f"transport/link/tls/{key}"
        for key in ("listen_private_key", "listen_certificate")
        if not any(name.startswith(key) for name in settings)  # listen_certificate_file …
        and not any(
            json.loads(config.get_json(f"transport/link/tls/{name}"))
            for name in (key, f"{key}_base64")
        )
    ]


def endpoints_of(config: zenoh.Config, kind: str, mode: str) -> list[str]:
    """The endpoints ``config`` listens on or connects to (``kind``) in ``mode``: a list,
    or (as zenoh's default, and a file a router shares with its clients) a list per mode, of
    which only its own."""
    endpoints = json.loads(config.get_json(f"{kind}/endpoints"))
    if isinstance(endpoints, dict):
        return list(endpoints.get(mode) or [])
    return list(endpoints)


def check_unix_listeners(endpoints: Sequence[str]) -> None:
    """Refuse (``ValueError``) a ``unixsock-stream`` endpoint that zenoh would take from
    someone: zenoh deletes whatever is at a listener's path before it binds there, and its
    lock file beside it (``<path>.lock``) when it closes, so a file there is lost
    (``unixsock-stream//etc/passwd`` under root removed it), and another process's socket is
    taken over. A path that is not a socket is refused, and so is a socket something answers
    on, or a lock that is not zenoh's (an empty file); a socket nobody answers on and its
    empty lock, left by a process that ended, are taken.
    """
    for endpoint in endpoints:
        path = unix_socket_path(endpoint)
        if path is None:
            continue
        _check_lock_file(endpoint, f"{path}.lock")
        try:
            if not stat.S_ISSOCK(os.lstat(path).st_mode):
                raise ValueError(
                    f"cannot listen on {endpoint}: {path} exists and is not a socket (zenoh "
                    f"would delete it to listen there): name a path of its own"
                )
            if _answered(path):
                raise ValueError(f"cannot listen on {endpoint}: a process listens on {path}")
        except FileNotFoundError:
            continue
        except OSError as exc:  # not ours to look at, or a socket that neither takes nor refuses
            why = exc.strerror or "no answer within 1 s"
            raise ValueError(f"cannot listen on {endpoint}: {path}: {why}") from exc


def unix_socket_path(endpoint: str) -> str | None:
    """The path of a ``unixsock-stream`` endpoint, without zenoh's metadata and
    configuration; ``None`` for an endpoint of another protocol."""
    if not endpoint.startswith("unixsock-stream/"):
        return None
    return re.split(r"[?#]", endpoint.removeprefix("unixsock-stream/"), maxsplit=1)[0]


def _check_lock_file(endpoint: str, lock: str) -> None:
    try:
        found = os.lstat(lock)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ValueError(f"cannot listen on {endpoint}: {lock}: {exc.strerror}") from exc
    if not stat.S_ISREG(found.st_mode) or found.st_size:
        raise ValueError(
            f"cannot listen on {endpoint}: {lock} is not zenoh's lock (zenoh would delete it "
            f"when it stops listening there): name a path of its own"
        )


def _answered(path: str) -> bool:
    """Whether something accepts a connection on the Unix socket at ``path`` (``False``: it
    is refused, nobody listens there)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(path)
        except ConnectionRefusedError:
            return False
    return True


_RUST_SOURCE = re.compile(r"\s+at /\S+?\.rs:\d+\.?")


def zenoh_reason(exc: BaseException) -> str:
    """The human part of a zenoh error: its first line without the " at <rust source>:<line>"
    zenoh appends to each message it wraps.

    >>> zenoh_reason(Exception("listener bound to tcp/h:1: [h:1: in use at /x/tcp.rs:61.] "
    ...                        "at /x/unicast.rs:338."))
    'listener bound to tcp/h:1: [h:1: in use]'
    """
    return _RUST_SOURCE.sub("", str(exc).splitlines()[0]).strip()


_LISTENER = re.compile(r"listener bound to (\S+?): ")


def session_refusal(exc: BaseException, in_use_hint: str) -> str:
    """What to tell when zenoh would not open the gateway's session (``exc``); an endpoint
    in use gets ``in_use_hint`` (who probably holds it).

    >>> session_refusal(Exception("Can not create a new TCP listener bound to "
    ...     "tcp/127.0.0.1:7447: [127.0.0.1:7447: Address already in use (os error 98)]"),
    ...     "another busgate demo or run?")
    'zenoh cannot listen on tcp/127.0.0.1:7447: it is in use (another busgate demo or run?)'
    """
    reason = zenoh_reason(exc)
    listener = _LISTENER.search(reason)
    if listener is not None and f"(os error {errno.EADDRINUSE})" in reason:
        return f"zenoh cannot listen on {listener.group(1)}: it is in use ({in_use_hint})"
    return f"cannot open the zenoh session: {reason}"


_PARSER_POSITION = re.compile(r"^\s*--> (?P<line>\d+):(?P<column>\d+)")
_PARSER_EXPECTED = re.compile(r"^\s*= (?P<msg>.+)$", re.M)
#: The Rust debug prints zenoh wraps a config file's refusal in (serde_json/json5, YAML, TOML).
_DEBUG_PRINTS = (
    re.compile(
        r'msg: "(?P<msg>.*?)",\s*location: Some\(Location \{ line: (?P<line>\d+), '
        r"column: (?P<column>\d+) \}\)"
    ),
    re.compile(r'Error\("(?P<msg>.*)", line: (?P<line>\d+), column: (?P<column>\d+)\)'),
    re.compile(r'message: "(?P<msg>.*?)", input: '),
)


def config_file_reason(exc: BaseException) -> str:
    """zenoh's reason for refusing a config file, on one line: where in the file when zenoh
    says (its json5 parser draws a caret diagram over several lines, serde a Rust debug
    print), and what is wrong there (tests/test_router.py has each form, from zenoh itself)."""
    text = str(exc)
    position, expected = _PARSER_POSITION.match(text), _PARSER_EXPECTED.search(text)
    if position is not None and expected is not None:  # json5's parser: a caret diagram
        reason = zenoh_reason(Exception(expected.group("msg")))
        return f"line {position['line']}, column {position['column']}: {reason}"
    reason = zenoh_reason(exc)
    for debug_print in _DEBUG_PRINTS:
        found = debug_print.search(reason)
        if found is not None:
            where = found.groupdict().get("line")
            at = f"line {where}, column {found['column']}: " if where is not None else ""
            return at + found["msg"]
    return reason


def clean(reason: str) -> str:
    """``reason`` without the Rust debug print around its message, when it has one."""
    found = re.search(r'msg: "(.*?)"(?:,\s*location|\s*\})', reason)
    return found.group(1) if found is not None else reason
