"""The dashboard's web side (Starlette): the page, its static files, the event stream, and
the only two things a browser may ask of the fleet: an e-stop (one gateway's, or the fleet's)
and the re-enable of one device.

Rules of this file:

1. Nothing but e-stop and enable reaches a gateway from here; both go through
   ``busgate.client`` under the dashboard's own zenoh account, so the deploy ACL decides what
   the dashboard may do (a viewer account stops nothing), not the browser.
2. A request that asks to act is refused, with nothing sent, unless it is a ``POST`` of a
   JSON object of at most ``MAX_BODY`` bytes, with ``Content-Type: application/json`` (a form
   on another site cannot send one without the CORS preflight this app never answers), from
   no other origin than the page's own, naming a gateway and device as names are spelled.
3. Every request's ``Host`` is one of the hosts the dashboard listens as (``allowed_hosts``):
   a page on another site that rebinds its DNS name to 127.0.0.1 gets a 400, not the fleet.
4. Replies to actions are JSON: ``{"ok": true, ...}`` or ``{"ok": false, "error": {"code",
   "message"}}`` with a 4xx status for a refused request and 502 when the gateway refused or
   did not answer.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from busgate.client.errors import GatewayError
from busgate.client.keys import check_name, split_name
from busgate.codecs.errors import BusgateError
from busgate.dashboard.hub import Hub

STATIC = Path(__file__).resolve().parent / "static"
MAX_BODY = 1024


class Actions(Protocol):
    """What the dashboard does for a browser (``busgate.dashboard.server``: the SDK)."""

    async def estop(self, gateway: str | None) -> None: ...

    async def enable(self, device: str) -> dict[str, Any]: ...


class Refused(Exception):
    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message


def refusal(status: int, code: str, message: str) -> JSONResponse:
    return JSONResponse({"ok": False, "error": {"code": code, "message": message}}, status)


async def _request_body(request: Request) -> dict[str, Any]:
    """The request's JSON object, checked as rule 2 says; else ``Refused``."""
    origin = request.headers.get("origin")
    if origin is not None and origin != f"{request.url.scheme}://{request.url.netloc}":
        raise Refused(403, "forbidden", f"requests from {origin[:100]} are not taken")
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != "application/json":
        raise Refused(415, "bad_request", "send application/json")
    raw = b""
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY:
            raise Refused(413, "bad_request", f"a request is at most {MAX_BODY} bytes")
    try:
        body = json.loads(raw)
    except (ValueError, RecursionError):
        raise Refused(400, "bad_request", "the body is not JSON") from None
    if not isinstance(body, dict):
        raise Refused(400, "bad_request", "the body is a JSON object")
    return body


def _checked(check: Any, *args: Any) -> Any:
    try:
        return check(*args)
    except BusgateError as exc:
        raise Refused(400, "bad_request", str(exc)) from None


def create_app(hub: Hub, actions: Actions, *, allowed_hosts: list[str]) -> Starlette:
    """The dashboard's ASGI app."""

    async def page(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def events(request: Request) -> Response:
        return StreamingResponse(
            hub.stream(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )

    async def estop(request: Request) -> Response:
        try:
            body = await _request_body(request)
            gateway = body.get("gateway")
            if gateway is not None:
                _checked(check_name, "gateway", gateway)
        except Refused as exc:
            return refusal(exc.status, exc.code, exc.message)
        try:
            await actions.estop(gateway)
        except BusgateError as exc:  # the session could not put it
            return refusal(502, "not_sent", str(exc))
        return JSONResponse({"ok": True, "estop": gateway or "*"})

    async def enable(request: Request) -> Response:
        try:
            body = await _request_body(request)
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
        except GatewayError as exc:
            return refusal(502, exc.code, exc.message)
        except BusgateError as exc:
            return refusal(502, "no_answer", str(exc))
        return JSONResponse({"ok": True, "device": device, "reply": reply})

    return Starlette(
        routes=[
            Route("/", page),
            Route("/events", events),
            Route("/api/estop", estop, methods=["POST"]),
            Route("/api/enable", enable, methods=["POST"]),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        middleware=[Middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts)],
    )
