"""The dashboard's web side (Starlette): the page, its static files, the event stream, and
the only three things a browser may ask of the fleet: an e-stop (one gateway's, or the
fleet's), the reset of one gateway's e-stop (never the fleet's), and the re-enable of one
device.

Rules of this file:

1. Nothing but e-stop, its reset and enable reaches a gateway from here; all three go through
   ``busgate.client`` under the dashboard's own zenoh account, so the deploy ACL decides what
   the dashboard may do (a viewer account stops nothing), not the browser.
2. A request that asks to act is refused, with nothing sent, unless it is a ``POST`` of a
   JSON object of at most ``MAX_BODY`` bytes, with ``Content-Type: application/json`` (a form
   on another site cannot send one without the CORS preflight this app never answers), from
   no origin but the dashboard's own (``http`` or ``https``, a host of ``hosts``, the port
   the request was sent to), naming a gateway and device as names are spelled.
3. Every request's ``Host`` names one of ``hosts`` (the names the dashboard answers to, port
   aside), never any: a page on another site that rebinds its DNS name to this machine gets a
   400 and reaches no route, whatever address the dashboard listens on.
4. Replies to actions are JSON: ``{"ok": true, ...}`` or ``{"ok": false, "error": {"code",
   "message"}}`` with a 4xx status for a refused request, 404 ``unknown_gateway`` when no
   gateway of the name is up (an e-stop was put all the same), and 502 when the gateway
   refused or did not answer; ``failure`` says which, for every route.
5. At most ``MAX_STREAMS`` event streams are open at once: the rest of the server's
   connections stay for pages and actions, whoever holds streams open without reading them.
   They are counted as each stream begins (``Hub.stream``: one past them ends at once), and
   only a ``GET`` opens one (a ``HEAD``'s body is dropped, so it never fell behind).
6. No response may be shown in another page's frame (``NEVER_FRAMED``): a page on another
   site that framed the dashboard could trick a click on its e-stop, reset or enable, whose
   requests would carry the dashboard's own host and origin.
7. A body is read as the gateway reads a payload (``decode_object``): a key given twice, or
   a number that is no number (``NaN``), is refused, never guessed.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Awaitable, Callable, Set
from pathlib import Path
from typing import Any, Protocol

from starlette.applications import Starlette
from starlette.datastructures import Headers
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from busgate.client.errors import GatewayError, UnknownGatewayError
from busgate.client.keys import check_name, split_name
from busgate.dashboard.hub import Hub
from busgate.errors import BusgateError, RefusedError
from busgate.schemas.payload import decode_object

STATIC = Path(__file__).resolve().parent / "static"
#: Live event streams at once (one a browser's page): past them a stream gets a 503, so that
#: held streams never take the connections a page, and its e-stop, need (rule 5).
MAX_STREAMS = 48
MAX_BODY = 1024
#: Rule 6, on every response: the old header and the one that replaced it.
NEVER_FRAMED = (
    (b"x-frame-options", b"DENY"),
    (b"content-security-policy", b"frame-ancestors 'none'"),
)
#: ``HOST[:PORT]`` as a ``Host`` header or an origin carries it: a DNS name (253 characters at
#: most) or an IPv4 address, or an IPv6 address in brackets.
HOST_AND_PORT = re.compile(
    r"(?:\[(?P<ipv6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9._-]{1,253}))(?::(?P<port>[0-9]{1,5}))?"
)


class Actions(Protocol):
    """What the dashboard does for a browser (``busgate.dashboard.server``: the SDK)."""

    async def estop(self, gateway: str | None) -> None: ...

    async def reset_estop(self, gateway: str) -> None: ...

    async def enable(self, device: str) -> dict[str, Any]: ...


class Refused(Exception):
    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message


def refusal(status: int, code: str, message: str) -> JSONResponse:
    return JSONResponse({"ok": False, "error": {"code": code, "message": message}}, status)


def failure(exc: BusgateError, unanswered: str) -> JSONResponse:
    """Rule 4: the reply to what the SDK raised, with ``unanswered`` as the code of a failure
    no gateway told (the session's, or no answer in time)."""
    if isinstance(exc, UnknownGatewayError):
        return refusal(404, exc.code, exc.message)
    if isinstance(exc, GatewayError):
        return refusal(502, exc.code, exc.message)
    return refusal(502, unanswered, str(exc))


def host_and_port(text: str) -> tuple[str, str | None] | None:
    """The host (lower case; an IPv6 address bare, in its short form) and the port of
    ``HOST[:PORT]``; ``None`` when ``text`` is not that."""
    found = HOST_AND_PORT.fullmatch(text)
    if found is None:
        return None
    if found["ipv6"] is None:
        return found["name"].lower(), found["port"]
    try:
        return ipaddress.IPv6Address(found["ipv6"]).compressed, found["port"]
    except ValueError:
        return None


def _is_own_origin(origin: str, host: str, hosts: Set[str]) -> bool:
    """Rule 2: ``origin`` is ``http`` or ``https`` (a proxy in front may speak TLS), on a host
    of ``hosts`` and on the port of the request's ``host``."""
    scheme, separator, rest = origin.partition("://")
    where, sent_to = host_and_port(rest), host_and_port(host)
    if scheme not in ("http", "https") or not separator or where is None or sent_to is None:
        return False
    return where[0] in hosts and where[1] == sent_to[1]


async def _request_body(request: Request, hosts: Set[str]) -> dict[str, Any]:
    """The request's JSON object, checked as rule 2 says; else ``Refused``."""
    origin = request.headers.get("origin")
    if origin is not None and not _is_own_origin(origin, request.headers.get("host", ""), hosts):
        raise Refused(403, "forbidden", f"requests from {origin[:100]} are not taken")
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != "application/json":
        raise Refused(415, "bad_request", "send application/json")
    raw = b""
    try:
        async for chunk in request.stream():
            raw += chunk
            if len(raw) > MAX_BODY:
                raise Refused(413, "bad_request", f"a request is at most {MAX_BODY} bytes")
    except ClientDisconnect:  # gone, or closed by the server for sending too slowly
        raise Refused(400, "bad_request", "the body did not come whole") from None
    try:
        return decode_object(raw, limit=MAX_BODY)
    except RefusedError as exc:
        raise Refused(400, "bad_request", f"the body: {exc}") from None


def _checked(check: Any, *args: Any) -> Any:
    try:
        return check(*args)
    except BusgateError as exc:
        raise Refused(400, "bad_request", str(exc)) from None


def _gateway(body: dict[str, Any]) -> str | None:
    """The gateway ``body`` names, spelled as names are; ``None`` when it names none."""
    gateway = body.get("gateway")
    return None if gateway is None else _checked(check_name, "gateway", gateway)


class _KnownHostsNeverFramed:
    """Rules 3 and 6, in front of every route."""

    def __init__(self, app: ASGIApp, hosts: Set[str]) -> None:
        self._app, self._hosts = app, hosts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self._app(scope, receive, send)
            return

        async def never_framed(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), *NEVER_FRAMED]}
            await send(message)

        host = Headers(scope=scope).get("host", "")
        found = host_and_port(host)
        if found is None or found[0] not in self._hosts:
            message = f"{host[:100]!r} is not a name this dashboard answers to"
            await refusal(400, "unknown_host", message)(scope, receive, never_framed)
            return
        await self._app(scope, receive, never_framed)


def create_app(hub: Hub, actions: Actions, *, hosts: Set[str]) -> Starlette:
    """The dashboard's ASGI app, answering as ``hosts`` (``host_and_port``'s form) alone."""

    async def page(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def events(request: Request) -> Response:
        if request.method != "GET":  # rule 5: a HEAD's body is dropped, its view never behind
            return refusal(405, "method_not_allowed", "the live view is a GET")
        if hub.browsers >= MAX_STREAMS:
            return refusal(503, "busy", f"{MAX_STREAMS} live views are open: close one")
        return StreamingResponse(
            hub.stream(MAX_STREAMS),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )

    async def to_gateway(
        request: Request, act: Callable[[Any], Awaitable[None]], done: str, *, fleet: bool
    ) -> Response:
        """An action on the gateway the body names (the fleet's when none is named, if
        ``fleet``), answered ``{"ok": true, done: gateway}``."""
        try:
            gateway = _gateway(await _request_body(request, hosts))
            if gateway is None and not fleet:
                raise Refused(400, "bad_request", 'name the gateway: {"gateway": "gw1"}')
        except Refused as exc:
            return refusal(exc.status, exc.code, exc.message)
        try:
            await act(gateway)
        except BusgateError as exc:
            return failure(exc, "not_sent")
        return JSONResponse({"ok": True, done: gateway or "*"})

    async def estop(request: Request) -> Response:
        return await to_gateway(request, actions.estop, "estop", fleet=True)

    async def reset_estop(request: Request) -> Response:  # a reset is never the fleet's
        return await to_gateway(request, actions.reset_estop, "reset_estop", fleet=False)

    async def enable(request: Request) -> Response:
        try:
            body = await _request_body(request, hosts)
            device = body.get("device")
            if not isinstance(device, str):
                raise Refused(400, "bad_request", 'name the device: {"device": "gw/la1"}')
            gateway, name = _checked(split_name, device)
            if gateway is None:
                raise Refused(400, "bad_request", f"name the device's gateway: gw/{name}")
        except Refused as exc:
            return refusal(exc.status, exc.code, exc.message)
        try:
            reply = await actions.enable(device)
        except BusgateError as exc:
            return failure(exc, "no_answer")
        return JSONResponse({"ok": True, "device": device, "reply": reply})

    return Starlette(
        routes=[
            Route("/", page),
            Route("/events", events),
            Route("/api/estop", estop, methods=["POST"]),
            Route("/api/reset_estop", reset_estop, methods=["POST"]),
            Route("/api/enable", enable, methods=["POST"]),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        middleware=[Middleware(_KnownHostsNeverFramed, hosts=hosts)],
    )
