"""The one core of the SDK: a client's zenoh session, and every exchange with gateways as a
``concurrent.futures.Future`` (what the exchanges carry: ``messages.py``); the sync face
(``sync.py``) waits on those futures, the asyncio face (``aio.py``) awaits them (both run the
same operations, ``surface.py``), so both do exactly the same on the wire.

Rules of this file:

1. Callbacks only hand over. A reply is parsed (none past ``MAX_REPLY``) and stored and a
   finished query settles its future on zenoh's own thread, where one slow callback would
   stall every other one of the session. A sample goes to its sinks (which may not block) on
   its subscription's thread (rule 5): a slow one holds up that subscription, and the whole
   session once its queue in zenoh is full.
2. Every command carries the client's id; the client's liveliness token
   (``<prefix>/clients/<id>``) is held from ``open`` to ``close``, so that a gateway drops
   the client's claims and streams when it goes (its lease, about 1 s by default).
3. A reply becomes a result or one of ``busgate.client.errors``; no ``zenoh.ZError`` leaves.
4. Gateways come and go (liveliness ``<prefix>/<gw>/alive``): a gateway going takes this
   client's claims on it (``on_gateway_gone``); subscriptions and queries resume on their own
   once it is back, as zenoh re-declares them.
5. Nothing of a client holds its program's exit. Python joins every non-daemon thread
   (``threading._shutdown``) before it runs any ``atexit`` handler, and zenoh calls a plain
   function given as a callback on a non-daemon ``threading.Thread`` of its own until the
   session closes: a program that never closed its client never ended. So zenoh is never
   given one: a query's callbacks run on zenoh's thread (``indirect=False``), and each
   subscription is declared with zenoh's channel and drained by a daemon thread of its own
   (as fast as zenoh's threads: a callback on zenoh's thread would cost each sample a Python
   thread state made and dropped, about 10 µs); a sample its sink fails is logged with its
   traceback once every ``FAILURE_TOLD_EVERY_S`` at most (a peer's flood of what the sink
   cannot take would fill the log), the failures between counted in the next line. A client
   never closed is closed at exit by a ``weakref.finalize`` (its registry holds no client,
   and none once closed), on a daemon thread given ``EXIT_CLOSE_S``: zenoh's close waits for
   its callbacks under way, and a subscription whose sink never returns leaves one under way
   once its queue is full (zenoh waits to put a sample in it); the exit must not wait for
   that (the process ends anyway, and the gateways see the client go). That close tells no
   subscription's reader that it ended (``subscribe``'s ``ended``): a daemon thread still
   waiting for a message ends with the program, where a wait woken to raise would print its
   traceback into the exit.
6. A close waits, at most ``DRAIN_END_S``, for the subscriptions' daemon threads to end. Each
   waits for its next sample in zenoh, without the interpreter, and takes the interpreter
   again when the closed session ends its wait; a program that returns from its close at
   once may be ending by then, and Python ends a thread that asks for the interpreter of a
   finalizing program where it stands, inside zenoh's code, which aborts the process
   ("FATAL: exception not rethrown", exit status 134, about one ``busgate send`` in 40 on a
   loaded host).
7. Ctrl-C ends a session's opening at once. ``zenoh.open`` cannot be interrupted, and waits
   up to its connect timeout (some 10 s) for an endpoint that takes the connection and never
   answers (a port some other program listens on, a host that drops the handshake): the
   program's handlers ran only after it, so a Ctrl-C held a ``busgate send`` 9 s and then
   printed a traceback. It runs on a daemon thread of its own (``_opened``), which the
   calling thread waits for as signals allow (a wait on a lock); a session that opens after
   its caller left is closed (on the asyncio face too, whose awaiting a deadline or a stop
   cancels: ``steps.Call``'s ``unwanted``). The caller that leaves (of either face:
   ``Call.left_wait_s``) waits ``LEFT_OPEN_WAIT_S`` at most for the opening, and that close,
   to end first: one that ends as the program does opens rule 6's window again (zenoh
   handing its thread back to an interpreter that is finalizing).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import socket
import threading
import time
import weakref
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, InvalidStateError
from pathlib import Path
from typing import Any

import zenoh

from busgate.client.errors import ConnectError
from busgate.client.keys import Keys, check_key, check_name
from busgate.client.messages import (
    MAX_LEASE_S,
    MAX_WAIT_S,
    MIN_LEASE_S,
    MIN_WAIT_S,
    UNPARSED,
    Answer,
    Answers,
    dumps,
    first_ok,
    seconds,
    then,
)
from busgate.errors import CommandError
from busgate.schemas.endpoints import ENDPOINT_FORM, host_of, is_endpoint
from busgate.schemas.payload import MAX_WHOLE_GATEWAY
from busgate.schemas.validation import cut
from busgate.schemas.zenoh_session import (
    MAX_RECEIVED,
    TLS_PROTOCOLS,
    session_config,
    zenoh_reason,
)

log = logging.getLogger(__name__)

#: The payload of zenoh's own error reply when a queryable did not answer in time.
ZENOH_TIMEOUT = b"Timeout"
#: The largest reply read, in bytes (``answer_of``): past it a reply is no gateway's, and
#: parsing it on zenoh's thread (rule 1) took a peer's 80 MB info to 1.3 GB and past the
#: query's timeout. A gateway's largest reply is its ``info`` (``MAX_WHOLE_GATEWAY``).
MAX_REPLY = MAX_WHOLE_GATEWAY

#: The longest endpoint shown whole in a refusal (one of 5,000 characters was echoed).
SHOWN_ENDPOINT_CHARS = 80
#: How long a client waits for an answer unless told otherwise (``connect``'s ``timeout``).
DEFAULT_TIMEOUT_S = 5.0
#: What a client's session may be: a router that listened on nothing would route for nobody
#: (``busgate router`` is the fleet's).
CLIENT_MODES = ("client", "peer")
#: The most of a client id another names that a refusal shows (a program's may be megabytes).
SHOWN_CLIENT_CHARS = 200
#: How long the close at interpreter exit of a client never closed may take (rule 5).
EXIT_CLOSE_S = 0.5
#: How long a caller that leaves an opening (a Ctrl-C) waits for zenoh to hand its thread
#: back (rule 7): a program that ends as that happens aborts, as in rule 6 (the gateway's
#: stop aborted so in 9 of 10 stops that came as its router answered).
LEFT_OPEN_WAIT_S = 0.5
#: How long a close waits for its subscriptions' threads to end (rule 6).
DRAIN_END_S = 0.5
#: A subscriber that fails sample after sample (a peer putting what it cannot take) has its
#: traceback logged once in this long, with a count of the failures not told.
FAILURE_TOLD_EVERY_S = 60.0
#: What a subscription is declared with: zenoh's own queue of samples, drained (rule 5).
CHANNEL: zenoh.handlers.DefaultHandler[Any] = zenoh.handlers.DefaultHandler()


def answer_of(reply: zenoh.Reply) -> Answer | None:
    """A zenoh reply as an ``Answer``; ``None`` for zenoh's own timeout reply. A payload past
    ``MAX_REPLY`` is left unread: an answer that is not ok, saying its size."""
    sample, error = reply.ok, reply.err
    answer = sample if sample is not None else error
    assert answer is not None  # a zenoh reply carries a sample or an error
    key = str(getattr(answer, "key_expr", ""))
    if (size := len(answer.payload)) > MAX_REPLY:
        unread = f"a reply of {size} bytes, more than any gateway answers ({MAX_REPLY}): unread"
        return Answer(key, unread, False)
    raw = answer.payload.to_bytes()
    if sample is None and raw == ZENOH_TIMEOUT:
        return None
    try:
        body = json.loads(raw)
    except UNPARSED:
        return Answer(key, raw.decode(errors="replace"), False)
    ok = sample is not None and isinstance(body, dict) and body.get("ok") is True
    return Answer(key, body, ok)


class Core:
    """One client's zenoh session: queries, puts, subscriptions, its liveliness token. What it
    is opened with is what ``connect`` takes (``surface.connecting``), as documented there."""

    def __init__(
        self,
        endpoints: Sequence[str] | str = "tcp/127.0.0.1:7447",
        *,
        client_id: str,
        prefix: str = "busgate",
        mode: str = "client",
        lease_s: float = 1.0,
        timeout: float = DEFAULT_TIMEOUT_S,
        config_file: str | Path | None = None,
        username: str | None = None,
        password: str | None = None,
        ca: str | Path | None = None,
    ) -> None:
        self.client_id = check_name("client", client_id)
        #: What numbers this client's follow targets and ends (``next_seq``).
        self._seq = itertools.count(time.time_ns())
        self.keys = Keys(prefix)
        self.timeout_s = seconds("timeout", timeout, MIN_WAIT_S, MAX_WAIT_S)
        if mode not in CLIENT_MODES:
            raise CommandError(
                f"mode must be {' or '.join(CLIENT_MODES)}, not {str(mode)[:80]!r}"
                " (a fleet's router is `busgate router`)"
            )
        seconds("lease_s", lease_s, MIN_LEASE_S, MAX_LEASE_S)
        endpoints = _endpoint_list(endpoints)
        for what, text in (("username", username), ("password", password)):
            if text is not None and not isinstance(text, str):
                raise CommandError(f"{what} must be a string, not {type(text).__name__}")
        for what, path in (("config_file", config_file), ("ca", ca)):
            if path is not None and not isinstance(path, str | Path):
                raise CommandError(f"{what} must be a path, not {type(path).__name__}")
        where = ", ".join(endpoints) or (str(config_file) if config_file else "no endpoint")
        try:
            config = session_config(
                mode=mode,
                connect=endpoints,
                config_file=config_file,
                lease_s=lease_s,
                username=username,
                password=password,
                ca=ca,
            )
            self.session = _opened(config)
        except ValueError as exc:  # a refusal that says what is wrong
            raise ConnectError(
                f"cannot open a zenoh session to {where}: {zenoh_reason(exc)}"
            ) from exc
        except zenoh.ZError as exc:
            hint = _endpoints_hint(endpoints) or _unopened_hint(endpoints, username, ca)
            raise ConnectError(
                f"cannot open a zenoh session to {where}: {zenoh_reason(exc)}{hint}",
                unreached=not hint and config_file is None,
            ) from exc
        self._lock = threading.Lock()
        self._exiting = threading.Event()  # set by the close at exit (rule 5)
        self._listeners: list[Callable[[str, bool], None]] = []
        self.gateways_up: set[str] = set()
        try:
            liveliness, alive = self.session.liveliness(), self.keys.alive("*")
            self._drains: list[threading.Thread] = []
            self._held: list[Any] = [
                liveliness.declare_token(self.keys.client(self.client_id)),
                _drained(
                    liveliness.declare_subscriber(alive, CHANNEL, history=True),
                    self._on_alive,
                    alive,
                    self._drains,
                ),
            ]
        except zenoh.ZError as exc:
            self.session.close()
            raise ConnectError(f"the session to {where} refused: {zenoh_reason(exc)}") from exc
        self._at_exit = weakref.finalize(
            self, _close_in_time, self.session, self._held, self._drains, self._exiting
        )

    def next_seq(self) -> int:
        """The next number of what this client sends a follow stream (a target, an
        ``end_follow``): increasing, from the wall clock's nanoseconds when the client opened,
        so a client that restarts under the same id numbers past its last run. The gateway
        orders a target against an end by it (``gateway.api.commands`` rule 3)."""
        return next(self._seq)

    # -- lifetime ----------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare everything (the token last but one) and close the session; again is a
        no-op. A client never closed is closed at interpreter exit (rule 5)."""
        if self._at_exit.detach() is not None:
            _close(self.session, self._held, self._drains)

    def require_open(self, key: str) -> None:
        """``CommandError`` once closed, as zenoh refuses a closed session's query on ``key``."""
        if not self._at_exit.alive:
            raise closed_reading(key)

    # -- exchanges ---------------------------------------------------------------------------

    def ask(
        self, key: str, payload: bytes | None = None, *, timeout_s: float | None = None
    ) -> Future:
        """A query on ``key`` (with ``payload``): a future of every ``Answer``, settled when
        zenoh says the query is over (all answered, or the timeout)."""
        if timeout_s is None:
            timeout_s = self.timeout_s
        seconds("timeout", timeout_s, MIN_WAIT_S, MAX_WAIT_S)
        answers = Answers()
        finished: Future = Future()

        def on_reply(reply: zenoh.Reply) -> None:
            answer = answer_of(reply)
            if answer is None:
                answers.timed_out = True
            else:
                answers.append(answer)

        def on_end() -> None:
            with contextlib.suppress(InvalidStateError):
                finished.set_result(answers)

        try:
            self.session.get(
                check_key(key),
                # Called on zenoh's own thread (indirect, it starts a thread per query: 0.5 ms
                # a command); both callbacks only store and settle (rule 1).
                zenoh.handlers.Callback(on_reply, on_end, indirect=False),
                payload=payload,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
        except zenoh.ZError as exc:
            raise CommandError(f"cannot query {key[:200]!r}: {zenoh_reason(exc)}") from exc
        return finished

    def command(self, key: str, body: dict[str, Any], *, timeout_s: float | None = None) -> Future:
        """A command to one gateway's key, carrying this client's id: a future of the ok
        reply's body, or of the error it is."""
        if body.get("client", self.client_id) != self.client_id:
            raise CommandError(
                f"a command of client {self.client_id!r} names client "
                f"{cut(repr(body['client']), SHOWN_CLIENT_CHARS)}"
            )
        waited = self.timeout_s if timeout_s is None else timeout_s
        gateway = self.keys.gateway_of(key)
        payload = dumps({**body, "client": self.client_id})
        if len(payload) > MAX_RECEIVED:  # dropped unseen: an audit's 3 MB waited its timeout
            raise CommandError(
                f"a command of {len(payload)} bytes to {key[:200]!r}: no gateway reads a "
                f"message over {MAX_RECEIVED} bytes"
            )
        asked = self.ask(key, payload, timeout_s=waited)
        return then(asked, lambda answers: first_ok(answers, key, waited, gateway))

    def put(self, key: str, payload: bytes, *, urgent: bool = False) -> None:
        """Fire and forget; ``urgent`` (an e-stop) goes first and is never dropped."""
        options: dict[str, Any] = {}
        if urgent:
            options = {
                "congestion_control": zenoh.CongestionControl.BLOCK,
                "priority": zenoh.Priority.REAL_TIME,
                "express": True,
            }
        try:
            self.session.put(check_key(key), payload, **options)
        except zenoh.ZError as exc:
            raise CommandError(f"cannot put on {key[:200]!r}: {zenoh_reason(exc)}") from exc

    def publisher(self, key: str) -> Callable[[bytes], None]:
        """A put of raw payloads on one key, declared once (a follow stream's)."""
        try:
            publisher = self.session.declare_publisher(check_key(key), express=True)
        except zenoh.ZError as exc:
            raise CommandError(f"cannot publish on {key[:200]!r}: {zenoh_reason(exc)}") from exc

        def put(payload: bytes) -> None:
            try:
                publisher.put(payload)
            except zenoh.ZError as exc:
                raise CommandError(f"cannot put on {key}: {zenoh_reason(exc)}") from exc

        put.undeclare = publisher.undeclare  # type: ignore[attr-defined]
        return put

    def subscribe(
        self,
        key: str,
        sink: Callable[[str, bytes], None],
        ended: Callable[[], None] | None = None,
    ) -> Callable[[], None]:
        """Hand each sample on ``key`` to ``sink(key, payload)`` (the subscription's thread: it
        may not block), then call ``ended()`` once the subscription has ended (undeclared,
        or its session closed: what waits for its next sample waits for nothing); returns
        what ends the subscription."""
        return self.subscribe_timed(key, lambda key, payload, ns: sink(key, payload), ended)

    def subscribe_timed(
        self,
        key: str,
        sink: Callable[[str, bytes, int], None],
        ended: Callable[[], None] | None = None,
    ) -> Callable[[], None]:
        """As ``subscribe``, with each sample's time in ns since the epoch: its zenoh
        timestamp where it carries one, else when it arrived here."""

        def on_sample(sample: zenoh.Sample) -> None:
            stamp = sample.timestamp
            ns = time.time_ns() if stamp is None else _timestamp_ns(stamp)
            sink(str(sample.key_expr), sample.payload.to_bytes(), ns)

        try:
            subscriber = self.session.declare_subscriber(check_key(key), CHANNEL)
        except zenoh.ZError as exc:
            raise CommandError(f"cannot subscribe to {key[:200]!r}: {zenoh_reason(exc)}") from exc
        exiting = self._exiting

        def end() -> None:
            if ended is not None and not exiting.is_set():  # rule 5: an exit tells nobody
                ended()

        _drained(subscriber, on_sample, key, self._drains, end)
        return lambda: _quietly(subscriber.undeclare)

    # -- gateways coming and going -----------------------------------------------------------

    def on_gateways(self, listener: Callable[[str, bool], None]) -> Callable[[], None]:
        """Call ``listener(gateway, alive)`` (zenoh's thread) when a gateway's token comes
        (``True``) or goes (``False``), first for each gateway up now; returns what stops it.
        ``CommandError`` once closed: it would never be called."""
        self.require_open(self.keys.alive("*"))
        with self._lock:
            self._listeners.append(listener)
            up = sorted(self.gateways_up)
        for gateway in up:
            listener(gateway, True)

        def stop() -> None:
            with self._lock, contextlib.suppress(ValueError):
                self._listeners.remove(listener)

        return stop

    def on_gateway_gone(self, listener: Callable[[str], None]) -> Callable[[], None]:
        """Call ``listener(gateway)`` (zenoh's thread) when a gateway's token goes."""
        return self.on_gateways(lambda gateway, alive: None if alive else listener(gateway))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        gateway = self.keys.gateway_in(str(sample.key_expr), "alive")
        if gateway is None:  # a token on busgate/*/alive is no gateway: it would stand for all
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if alive:
                self.gateways_up.add(gateway)
            else:
                self.gateways_up.discard(gateway)
            listeners = list(self._listeners)
        for listener in listeners:  # the claims' own among them: one's failure stops none
            try:
                listener(gateway, alive)
            except Exception:
                log.exception("a listener to gateway %r %s failed", gateway, _CAME[alive])


_CAME = {True: "coming", False: "going"}


def _drained(
    subscriber: Any,
    on_sample: Callable[[Any], None],
    key: str,
    drains: list[threading.Thread],
    ended: Callable[[], None] | None = None,
) -> Any:
    """``subscriber`` (declared with ``CHANNEL``) drained into ``on_sample`` by a daemon thread
    of its own until it is undeclared or the session closes (rule 5), then ``ended()``; the
    thread kept in ``drains`` for the close to wait for (rule 6)."""

    def drain() -> None:
        told_at, untold = -math.inf, 0  # a sink that fails each sample logs once in a while
        for sample in subscriber:
            try:
                on_sample(sample)
            except Exception:  # one sample that fails a sink must not end the subscription
                moment = time.monotonic()
                if moment - told_at < FAILURE_TOLD_EVERY_S:
                    untold += 1
                    continue
                since = f" ({untold} more since the last told)" if untold else ""
                log.exception("a sample on %s failed its subscriber%s", key[:200], since)
                told_at, untold = moment, 0
        if untold:
            log.error("%d more samples on %s failed its subscriber", untold, key[:200])
        if ended is not None:
            try:
                ended()
            except Exception:
                log.exception("the end of the subscription to %s failed its subscriber", key[:200])

    thread = threading.Thread(target=drain, name=f"busgate {key[:100]}", daemon=True)
    drains[:] = [t for t in drains if t.is_alive()]  # an undeclared subscription's has ended
    drains.append(thread)
    thread.start()
    return subscriber


def _opened(config: zenoh.Config) -> zenoh.Session:
    """``zenoh.open(config)``, waited for as signals allow (rule 7)."""
    opening: Future[zenoh.Session] = Future()

    def open_session() -> None:
        try:
            opening.set_result(zenoh.open(config))
        except BaseException as exc:  # handed to the caller as it is
            opening.set_exception(exc)

    opener = threading.Thread(target=open_session, name="zenoh-open", daemon=True)
    opener.start()
    try:
        return opening.result()
    except BaseException:  # the caller leaves: a session that opens after all is closed
        opening.add_done_callback(_close_unwanted)
        opener.join(LEFT_OPEN_WAIT_S)
        raise


def _close_unwanted(opening: Future[zenoh.Session]) -> None:
    if opening.exception() is None:
        opening.result().close()


def closed_reading(key: str) -> CommandError:
    """What reading ``key`` meets once the client is closed, as a closed session's query
    does."""
    return CommandError(f"cannot read {key[:200]!r}: session closed")


def _close(session: zenoh.Session, held: list[Any], drains: list[threading.Thread]) -> None:
    held.clear()
    with contextlib.suppress(zenoh.ZError):
        session.close()
    deadline = time.monotonic() + DRAIN_END_S
    for thread in drains:  # rule 6; a sink that closes its own client does not wait for itself
        if thread is not threading.current_thread():
            thread.join(max(deadline - time.monotonic(), 0.0))


def _endpoint_list(endpoints: object) -> list[str]:
    """``endpoints`` as a list: one endpoint, or several (a program may pass a tuple, or a
    generator); a ``CommandError`` for anything else (a port number alone, a list with one)."""
    listed: list[object] = [endpoints]
    if isinstance(endpoints, Iterable) and not isinstance(endpoints, str | bytes | bytearray):
        listed = list(endpoints)
    texts = [endpoint for endpoint in listed if isinstance(endpoint, str)]
    if len(texts) < len(listed):
        wrong = next(endpoint for endpoint in listed if not isinstance(endpoint, str))
        raise CommandError(
            "endpoints must be a zenoh endpoint ('tcp/host:port') or a list of them, "
            f"not {type(wrong).__name__}"
        )
    return texts


def _endpoints_hint(endpoints: Sequence[str]) -> str:
    """What is wrong with an endpoint itself, which zenoh's "unable to connect" does not say:
    one that is none busgate knows (another protocol, a space before it), or whose host name
    does not resolve here; ``""`` when none is.

    >>> _endpoints_hint(["tcp/127.0.0.1:7447", " tcp/127.0.0.1:7447"])[:40]
    " (' tcp/127.0.0.1:7447' is no endpoint: "
    >>> _endpoints_hint(["tcp/a..b:7447"])  # refused before any lookup leaves the host
    " (its host 'a..b' does not resolve here)"
    """
    for endpoint in endpoints:
        if not is_endpoint(endpoint):
            return f" ({cut(endpoint, SHOWN_ENDPOINT_CHARS)!r} is no endpoint: {ENDPOINT_FORM})"
        host = host_of(endpoint)
        if host is not None and not _resolves(host):
            return f" (its host {host!r} does not resolve here)"
    return ""


def _resolves(host: str) -> bool:
    try:
        socket.getaddrinfo(host, None)
    except (socket.gaierror, UnicodeError):
        return False
    return True


def _unopened_hint(endpoints: Sequence[str], username: str | None, ca: object) -> str:
    """What may have kept zenoh from opening a session, which its words do not say (it turns
    a refused login or TLS handshake away as it does a port nobody listens on); ``""`` when
    no account or TLS link was involved.

    >>> _unopened_hint(["tls/gw:7447"], "operator", None)
    " (a tls/ endpoint needs the CA that signed the gateway's certificate: ca=, --ca)"
    >>> _unopened_hint(["tcp/gw:7447"], None, None)
    ''
    """
    secured = any(endpoint.startswith(TLS_PROTOCOLS) for endpoint in endpoints)
    if secured and ca is None:
        account = "" if username is not None else "; and an account if it takes them: --user"
        return (
            " (a tls/ endpoint needs the CA that signed the gateway's certificate: ca=, --ca"
            f"{account})"
        )
    if username is not None:
        return " (a wrong user name or password, or a gateway that takes none, is refused so too)"
    if secured:
        return (
            " (nobody listening there, or a gateway that takes accounts refusing a session"
            " without one: username=, --user)"
        )
    return ""


def _close_in_time(
    session: zenoh.Session,
    held: list[Any],
    drains: list[threading.Thread],
    exiting: threading.Event,
) -> None:
    """``_close`` of a client never closed, waited for at most ``EXIT_CLOSE_S``, telling no
    subscriber that its subscription ended (rule 5)."""
    exiting.set()
    closing = threading.Thread(
        target=_close, args=(session, held, drains), name="busgate-client-close", daemon=True
    )
    closing.start()
    closing.join(EXIT_CLOSE_S)
    if closing.is_alive():
        log.warning(
            "a busgate client's session was still closing %g s into the exit (a callback under "
            "way does not return): the program ends without waiting for it",
            EXIT_CLOSE_S,
        )


def _timestamp_ns(stamp: zenoh.Timestamp) -> int:
    moment = stamp.get_time()  # a datetime, in UTC
    return int(moment.timestamp()) * 1_000_000_000 + moment.microsecond * 1_000


def _quietly(undeclare: Callable[[], None]) -> None:
    with contextlib.suppress(zenoh.ZError):
        undeclare()
