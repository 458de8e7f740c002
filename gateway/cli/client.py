"""``busgate send`` and ``busgate watch``: a client's view of gateways, built on
``busgate.client`` (the SDK's raw keys: these tools take any key expression, and print what
comes back as it came).

send: one get (or, with ``--put``, one fire-and-forget put) of a JSON command on a device's
``cmd`` key, the payload as given (the gateway judges it; a put's, which gets no reply, must
be a JSON object as the gateway reads one, or empty, or nothing is sent; an ``estop`` key's
put goes whatever it carries). The device is named as the SDK names it: ``la1`` on
whichever gateway has it, ``gw1/la1`` on gateway ``gw1`` (which answers ``unknown_device``
itself when it lacks the device); any other target with a ``/`` is the key expression. A bare
name that more than one gateway has (their ``info``) is refused with nothing sent, as the
SDK's ``AmbiguousError``: in a fleet, ``la1`` would move every robot's ``la1``. Exit
status 0 when every reply has ``"ok": true``, 1 when any reply is an error or, for a bare
device name, when gateways answer (their ``info``) but none has the device
(``unknown_device``: a gateway leaves a fleet-wide command for a device it lacks
unanswered), 2 when nobody answered (or no session opened, or a put's command is not JSON, or a
put's key reached no gateway up: it went first, nobody took it).

watch: subscribes to the state of devices and the statistics of buses, keeps the latest of
each (``watch_table.py``), and redraws a table at most ``REDRAW_HZ`` times a second. Rules:
the SDK's callbacks (zenoh's threads) only store under a lock; all printing happens on the
main thread; the client is closed in ``finally``; while watching, Ctrl-C only sets an event
the main thread waits on, never raises wherever that thread happens to be (a ``with`` block
is not safe from an asynchronous ``KeyboardInterrupt``: one that lands as the table's lock is
taken leaves it held, and a callback waiting for it holds the session's close up; under a
loaded host a watch ended by Ctrl-C hung past 30 s).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

import busgate.client as bc
from busgate.client.base import name_hint
from busgate.client.keys import Keys, check_key, check_name, intersects, split_name
from busgate.client.messages import MAX_WAIT_S, MIN_WAIT_S, NOTHING_THERE
from busgate.errors import CommandError, RefusedError
from busgate.gateway.cli.arguments import seconds, seconds_from
from busgate.gateway.cli.client_session import add_session_options, open_client
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.gateway.cli.watch_table import WatchTable
from busgate.schemas.api import InfoReply
from busgate.schemas.payload import decode_object
from busgate.schemas.validation import printable, shown

REDRAW_HZ = 5
NO_ANSWER, ERROR_REPLY = 2, 1


# -- the command line -----------------------------------------------------------------------


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    send = subparsers.add_parser(
        "send",
        description="Send a JSON command to a device's cmd key and print each reply. A bare "
        "device name is looked up in every gateway's info and sent to the one that has it "
        "(refused, nothing sent, when several have it: name one as <gateway>/<device>); "
        "<gateway>/<device> means <prefix>/<gateway>/dev/<device>/cmd; any other argument "
        "with a '/' is used as the key expression as given. Exit status: 0 all replies ok, 1 "
        "an error reply or no gateway has the device (unknown_device), 2 nobody answered, no "
        "session opened, several gateways have the device, or, with --put, a command that is "
        "not JSON (nothing is sent) or a key that reached no gateway up (it went; nobody took "
        "it).",
    )
    send.add_argument(
        "target",
        help="a device name, gateway/device, or a key expression such as busgate/gw1/bus/uart0/cmd",
    )
    send.add_argument("command", help='the JSON command, e.g. \'{"op":"move","position":1000}\'')
    send.add_argument(
        "--timeout",
        type=seconds_from(MIN_WAIT_S, MAX_WAIT_S),
        default=2.0,
        help="seconds to wait for replies (default 2)",
    )
    send.add_argument("--pretty", action="store_true", help="indent the printed replies")
    send.add_argument(
        "--put",
        action="store_true",
        help="put instead of get: no reply (errors go to the gateway's events key); it ends "
        "once a gateway the key reaches is seen up",
    )
    add_session_options(send)
    send.set_defaults(handler=run_send)

    watch = subparsers.add_parser(
        "watch",
        description="Show the latest state of every device and the statistics of every bus, "
        "refreshed in place. The selector narrows what is shown: a gateway name, or a key "
        "expression (default <prefix>/**).",
    )
    watch.add_argument(
        "selector",
        nargs="?",
        default=None,
        help="a gateway name or a key expression (default <prefix>/**)",
    )
    watch.add_argument(
        "--once",
        action="store_true",
        help="print the table once after --seconds and exit (1 if nothing seen)",
    )
    watch.add_argument(
        "--seconds",
        type=seconds,
        default=None,
        help="how long to listen (default 1.5 with --once, else until Ctrl-C)",
    )
    add_session_options(watch)
    watch.set_defaults(handler=run_watch)


# -- send -----------------------------------------------------------------------------------


def command_key(prefix: str, target: str) -> str:
    """The key a ``send`` goes to: a device on every gateway, one on a gateway named as the
    SDK names it (``split_name``), else the key expression given.

    >>> command_key("busgate", "la1"), command_key("busgate", "gw1/la1")
    ('busgate/*/dev/la1/cmd', 'busgate/gw1/dev/la1/cmd')
    >>> command_key("busgate", "busgate/gw1/bus/uart0/cmd")
    'busgate/gw1/bus/uart0/cmd'
    """
    if "/" not in target:  # one device's name (a ``*`` would be every device's)
        try:
            return Keys(prefix).device("*", split_name(target, "device")[1], "cmd")
        except CommandError as exc:
            raise CommandError(
                f"{exc}; a target with a '/' is a key expression, taken as given"
                f" (e.g. {Keys(prefix).device('*', '*', 'cmd')})"
            ) from None
    try:
        gateway, device = split_name(target)
    except CommandError:  # more than <gateway>/<device>, or a wildcard: a key expression
        return target
    return target if gateway is None else Keys(prefix).device(gateway, device, "cmd")


def run_send(args: argparse.Namespace) -> int:
    text_arguments(args.target, args.command, args.prefix)
    key = check_key(command_key(args.prefix, args.target))
    payload = args.command.encode()
    if args.put and not _put_judged(key, payload, args.prefix):
        return NO_ANSWER
    bare_name = "/" not in args.target
    with open_client(args, "send") as client:
        gateways = gateway_devices(client.gateways(args.timeout)) if bare_name else {}
        if bare_name:
            holder = _one_gateway_with(args, gateways)
            if holder is None:
                return _no_holder(args, key, gateways)
            key = command_key(args.prefix, f"{holder}/{args.target}")
        if args.put:
            client.put(key, payload)
            return _put_reached(client, key, args)
        answers = client.query(key, payload, timeout=args.timeout)
        outcomes = list(answers)
    if not outcomes:
        return _no_reply(key, waited=args.timeout if answers.timed_out else None)
    status = 0
    for answer in outcomes:  # printable: a reply is a peer's text, escapes and all
        body = json.dumps(answer.body, indent=2 if args.pretty else None, ensure_ascii=False)
        print(printable(body, lines=True))
        if not answer.ok:
            code, message = (str(answer.error.get(part)) for part in ("code", "message"))
            print(f"busgate send: {printable(code, 64)}: {printable(message, 500)}",
                  file=sys.stderr)  # fmt: skip
            status = ERROR_REPLY
    return status


def text_arguments(*arguments: str) -> None:
    """``CommandError`` for a name, key or command given in bytes that are no UTF-8 (Python
    keeps each such byte as a lone surrogate, ``os.fsdecode``'s): it is no key, nor JSON.
    (A path may be any bytes: only these are judged.)"""
    for argument in arguments:
        for char in argument:
            if "\udc80" <= char <= "\udcff":
                raise CommandError(
                    f"the argument {argument!r} is not UTF-8 text (the byte "
                    f"0x{ord(char) - 0xDC00:02x}): nothing was done"
                )


def _one_gateway_with(args: argparse.Namespace, gateways: dict[str, set[str]]) -> str | None:
    """For a bare device name: the one gateway of ``gateways`` (their devices) that has it,
    ``None`` when none does; ``CommandError`` when several do (nothing is sent)."""
    holders = sorted(gateway for gateway, names in gateways.items() if args.target in names)
    if len(holders) > 1:
        raise CommandError(
            f"{len(holders)} gateways have a device {args.target!r} ({', '.join(holders)}): "
            f"name one, e.g. {holders[0]}/{args.target}; nothing was sent"
        )
    return holders[0] if holders else None


def _no_holder(args: argparse.Namespace, key: str, gateways: dict[str, set[str]]) -> int:
    """No gateway said it has the bare name's device: nothing is sent, never the command to
    every gateway's key (a gateway that did not answer in time, or whose info was no
    gateway's, would carry it out, and in a fleet so would every robot's). Those that
    answered are named (exit 1); none answering is exit 2."""
    if gateways:
        hint = name_hint(args.target, (name for names in gateways.values() for name in names))
        print(
            f"busgate send: unknown_device: no device {args.target!r} on the gateways that "
            f"answered ({', '.join(sorted(gateways))}{hint}): nothing was sent",
            file=sys.stderr,
        )
        return ERROR_REPLY
    info = Keys(args.prefix).info("*")
    print(
        f"busgate send: no gateway answered on {info} within {args.timeout:g} s: nothing was "
        f"sent to {key}",
        file=sys.stderr,
    )
    return NO_ANSWER


def _put_judged(key: str, payload: bytes, prefix: str) -> bool:
    """Whether a put may go: a put gets no reply, so a command the gateway would refuse as no
    JSON object (a tired operator's quotes lost to the shell, a key given twice, ``NaN``) is
    refused here, where someone reads the refusal, rather than by the gateway as an event
    nobody watching ``send`` sees. An empty or blank payload goes, and anything put on a key
    that reaches a gateway's e-stop (``estop``, ``**``): the e-stop takes any payload, and is
    never held back here."""
    if not payload.strip() or intersects(key, Keys(prefix).estop("*")):
        return True
    try:
        decode_object(payload)
    except RefusedError as exc:
        print(f"busgate send: the command is not JSON the gateway takes ({exc}): nothing was sent",
              file=sys.stderr)  # fmt: skip
        return False
    return True


def _put_reached(client: bc.Client, key: str, args: argparse.Namespace) -> int:
    """After a put (it went first: an e-stop is never slowed by a check), whether a gateway
    its key reaches is up (its liveliness token; at once for one the session has seen): 0,
    else a line saying the put reached nobody and exit 2. An e-stop put on a misspelt
    gateway, or over a link that reached none, ended as silently as one carried out. A key
    outside the prefix is not judged."""
    keys = Keys(args.prefix)
    if not key.startswith(f"{args.prefix}/"):
        return 0
    addressed = keys.alive(keys.gateway_of(key))
    reached = threading.Event()

    def seen(gateway: str, alive: bool) -> None:
        if alive and intersects(addressed, keys.alive(gateway)):
            reached.set()

    stop_watching = client.on_gateways(seen)
    try:
        if reached.wait(args.timeout):
            return 0
    finally:
        stop_watching()
    print(f"busgate send: no gateway under {key} is up (none seen within {args.timeout:g} s): "
          "the put reached nobody", file=sys.stderr)  # fmt: skip
    return NO_ANSWER


#: The last chunk of the API's keys that take puts only (docs/api.md): a get finds nobody.
PUT_ONLY_LEAVES = frozenset({"estop", "reset", "follow", "twist"})


def _no_reply(key: str, *, waited: float | None) -> int:
    """Nothing came back on ``key`` (in the ``waited`` seconds, when zenoh did wait; exit 2):
    on a key that takes puts only (an e-stop, say), the line says so, since nothing was
    done."""
    within = "" if waited is None else f" within {waited:g} s"
    puts_only = key.rsplit("/", 1)[-1] in PUT_ONLY_LEAVES
    if puts_only:
        hint = f": {key} takes puts, not gets: nothing was done (send --put)"
    elif waited is not None:  # it went: an answer later than the wait is not heard
        hint = ": the command went, and may have been carried out (see the device's state)"
    else:  # zenoh knew nobody who would take it
        hint = f": {NOTHING_THERE}"
    print(f"busgate send: nobody answered on {key}{within}{hint}", file=sys.stderr)
    return NO_ANSWER


def gateway_devices(infos: dict[str, InfoReply]) -> dict[str, set[str]]:
    """The devices of each gateway, from their ``info``."""
    return {
        gateway: {device.name for bus in info.buses for device in bus.devices}
        for gateway, info in infos.items()
    }


# -- watch ----------------------------------------------------------------------------------


def watch_keys(prefix: str, selector: str | None) -> tuple[str, str, str]:
    """(state key, stats key, filter) for a ``watch`` selector.

    >>> watch_keys("busgate", None)
    ('busgate/*/dev/*/state', 'busgate/*/bus/*/stats', 'busgate/**')
    >>> watch_keys("busgate", "gw1")
    ('busgate/gw1/dev/*/state', 'busgate/gw1/bus/*/stats', 'busgate/gw1/**')
    """
    if selector is None or selector == "**":  # every gateway's
        return f"{prefix}/*/dev/*/state", f"{prefix}/*/bus/*/stats", f"{prefix}/**"
    if "/" not in selector:  # a gateway's name, or a pattern of names (``*``, ``robot$*``)
        if "*" not in selector:
            try:
                check_name("gateway", selector)
            except CommandError as exc:  # 'la 1' was watched for, and nothing was seen
                raise CommandError(
                    f"{exc}; a selector with a '/' is a key expression, taken as given"
                    f" (e.g. {prefix}/*/dev/la1/state)"
                ) from None
        return (
            f"{prefix}/{selector}/dev/*/state",
            f"{prefix}/{selector}/bus/*/stats",
            f"{prefix}/{selector}/**",
        )
    return f"{prefix}/*/dev/*/state", f"{prefix}/*/bus/*/stats", selector


def run_watch(args: argparse.Namespace) -> int:
    text_arguments(args.selector or "", args.prefix)
    state_key, stats_key, selector = watch_keys(args.prefix, args.selector)
    try:
        for key in (selector, state_key, stats_key):
            check_key(key)
    except CommandError as exc:  # a pattern of names whose keys zenoh refuses: said as typed
        if args.selector is None or "/" in args.selector:
            raise
        raise CommandError(
            f"{shown(args.selector)} is no gateway name or pattern of names: * alone, or "
            "zenoh's $* within a name (robot$*)"
        ) from exc
    table = WatchTable()
    seconds = args.seconds if args.seconds is not None else (1.5 if args.once else None)
    with open_client(args, "watch") as client:
        _subscribe(client, table, Keys(args.prefix), selector, state_key, stats_key)
        gateway = state_key.split("/")[-4]
        answered = client.gateways(1.0)
        for name, info in answered.items():
            if gateway in ("*", name):
                seeding = info.model_dump(mode="json")  # the table holds what came as JSON
                table.seed(seeding, lambda key: intersects(selector, f"{args.prefix}/{key}"))
        if args.once:
            _wait(seconds)
        else:
            _wait_showing_live(table, sys.stdout, seconds)
    if args.once:
        print("\n".join(table.render(time.monotonic())))
        if table.empty:  # a misspelt gateway, as often as not: those that answer are named
            up = ", ".join(sorted(answered)) or "none"
            print(f"busgate watch: nothing seen on {selector} in {seconds:g} s (the gateways "
                  f"that answer: {up})", file=sys.stderr)  # fmt: skip
            return 1
    return 0


def _subscribe(
    client: bc.Client, table: WatchTable, keys: Keys, selector: str, state_key: str, stats_key: str
) -> None:
    """Each state and statistics into ``table``; a sample whose key names no gateway and
    device or bus (a put on ``busgate/**/state`` reaches these subscriptions too) is dropped."""

    def handler(
        update: Callable[[str, Any, float], None], room: str, leaf: str
    ) -> Callable[[str, Any], None]:
        def on_sample(key: str, body: Any) -> None:
            named = keys.names_in(key, room, leaf) is not None
            if body is not None and named and intersects(selector, key):
                update(key, body, time.monotonic())

        return on_sample

    client.subscribe(state_key, handler(table.update_state, "dev", "state"))
    client.subscribe(stats_key, handler(table.update_stats, "bus", "stats"))


def _wait(seconds: float | None) -> None:
    pressed = threading.Event()  # Ctrl-C or SIGTERM: the watch ends as at its time's end
    with stopped_by_signals(pressed):
        pressed.wait(seconds)


def _wait_showing_live(table: WatchTable, out: TextIO, seconds: float | None) -> None:
    """Redraw (tty) or print changed rows (pipe) until ``seconds`` pass or Ctrl-C."""
    tty = out.isatty()
    deadline = None if seconds is None else time.monotonic() + seconds
    pressed = threading.Event()
    with stopped_by_signals(pressed):
        while deadline is None or time.monotonic() < deadline:
            if pressed.wait(1 / REDRAW_HZ):
                return
            now = time.monotonic()
            if tty:
                _redraw(out, table.render(now))
            else:
                for line in table.changed_lines(now):
                    print(line, file=out, flush=True)


def _redraw(out: TextIO, lines: list[str]) -> None:
    # Cursor home, each line cleared to its end, then everything below: no flicker.
    out.write("\x1b[H" + "".join(f"{line}\x1b[K\n" for line in lines) + "\x1b[J")
    out.flush()
