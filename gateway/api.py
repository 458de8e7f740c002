"""The gateway's public API without zenoh: a client's payload in, a JSON reply out.

The bridge (the only zenoh module) hands payloads here and sends back what comes out; so
every rule of the API is tested without a network. Rules of this file:

1. A payload is refused before anything reaches a bus when it is over 64 KiB, not UTF-8, not
   JSON (NaN and infinities included), not an object, or not a valid command; the reply says
   why with a stable code (``not_utf8``, ``not_json``, ``too_large``, ``bad_command``,
   ``out_of_range``, ``unknown_device`` …) and a human message.
2. Claims: a client may hold exclusive motion control of a device; others get ``claimed``
   (naming the holder) until release, the TTL lapses, or the holder's liveliness goes. Reads
   and e-stops are never refused.
3. Deadman: when a client goes, its claims are released, its follow streams stop, and a
   ZLAC706 whose speed it commanded is brought to 0 rpm at once.
4. Nothing here blocks: commands go to the bus runners and come back as futures.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from pydantic import ValidationError

from busgate.codecs.errors import BusgateError, CommandError, EncodeError
from busgate.gateway.drivers.base import DeviceEvent, Driver
from busgate.gateway.group import group_command, scan_requests, scan_result
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.api import BusGroupMove, BusScan, Claim, Release
from busgate.schemas.errors import describe_validation_error

MAX_PAYLOAD = 64 * 1024
#: Ops a claim never blocks: they read, or they stop.
UNCLAIMED_OPS = frozenset({"status", "read", "ping", "monitor", "estop", "disable"})
#: Pydantic error types that mean "a value outside its range", reported as ``out_of_range``.
RANGE_ERRORS = frozenset({"less_than", "less_than_equal", "greater_than", "greater_than_equal",
                          "multiple_of", "too_short", "too_long"})


class ApiError(BusgateError):
    """A refusal with its stable code (one of ``busgate.schemas.api.ERROR_CODES``)."""

    code = "refused"

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def ok_reply(**fields: Any) -> dict[str, Any]:
    return {"ok": True, **fields}


def error_reply(exc: BaseException) -> dict[str, Any]:
    """The error envelope for ``exc``: its stable code, or ``internal`` for a bug."""
    code = exc.code if isinstance(exc, BusgateError) else "internal"
    return {"ok": False, "error": {"code": code, "message": str(exc) or type(exc).__name__}}


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def decode_object(payload: bytes) -> dict[str, Any]:
    """Bytes off the network to a JSON object, or ``ApiError`` saying what is wrong."""
    if len(payload) > MAX_PAYLOAD:
        raise ApiError("too_large", f"payload of {len(payload)} bytes; at most {MAX_PAYLOAD}")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ApiError("not_utf8", f"payload is not UTF-8: {exc.reason}") from exc
    try:
        value = json.loads(text, parse_constant=_reject_constant)
    except ValueError as exc:
        raise ApiError("not_json", f"payload is not JSON: {exc}") from exc
    if not isinstance(value, dict):
        raise ApiError("bad_command", "a command is a JSON object")
    return value


def refusal(exc: ValidationError | CommandError) -> ApiError:
    """A validation failure as ``out_of_range`` (a value outside its bounds) or
    ``bad_command`` (anything else: unknown op, missing or extra field, wrong type)."""
    cause = exc if isinstance(exc, ValidationError) else exc.__cause__
    if isinstance(cause, ValidationError):
        types = {error["type"] for error in cause.errors()}
        code = "out_of_range" if types and types <= RANGE_ERRORS else "bad_command"
        return ApiError(code, f"invalid command: {describe_validation_error(cause)}")
    if isinstance(exc, EncodeError):
        return ApiError("out_of_range", str(exc))
    return ApiError(exc.code, str(exc))


@dataclass(slots=True)
class Holder:
    client: str
    until: float


class ClaimTable:
    """Who holds which device, until when. Thread-safe: zenoh threads and the loop use it."""

    def __init__(self) -> None:
        self._holders: dict[str, Holder] = {}
        self._lock = threading.Lock()

    def claim(self, device: str, client: str, ttl_s: float, now: float) -> None:
        with self._lock:
            self._check(device, client, now)
            self._holders[device] = Holder(client, now + ttl_s)

    def release(self, device: str, client: str, now: float) -> None:
        with self._lock:
            self._check(device, client, now)
            self._holders.pop(device, None)

    def check(self, device: str, client: str | None, now: float) -> None:
        with self._lock:
            self._check(device, client, now)

    def holder(self, device: str, now: float) -> str | None:
        with self._lock:
            held = self._holders.get(device)
            return held.client if held and held.until > now else None

    def drop_client(self, client: str) -> list[str]:
        with self._lock:
            devices = [d for d, held in self._holders.items() if held.client == client]
            for device in devices:
                del self._holders[device]
            return devices

    def _check(self, device: str, client: str | None, now: float) -> None:
        held = self._holders.get(device)
        if held is None or held.until <= now:
            self._holders.pop(device, None)
            return
        if held.client != client:
            raise ApiError("claimed", f"{device} is claimed by {held.client!r}")


class GatewayApi:
    """Every device and bus of the gateway, as clients see them."""

    def __init__(
        self,
        name: str,
        runners: dict[str, BusRunner],
        *,
        clock: Callable[[], float],
        on_event: Callable[[DeviceEvent], None] = lambda event: None,
    ) -> None:
        self.name = name
        self.runners = runners
        self.clock = clock
        self.on_event = on_event
        self.claims = ClaimTable()
        self.devices: dict[str, tuple[BusRunner, Driver]] = {
            device: (runner, driver)
            for runner in runners.values()
            for device, driver in runner.drivers.items()
        }
        self._speed_clients: dict[str, str] = {}  # zlac706 device → client that set its speed
        self._stream_clients: dict[str, str] = {}  # device → client of its follow stream

    # -- commands ---------------------------------------------------------------------------

    def command(self, device: str, payload: bytes) -> Future:
        """Validate a device command and hand it to its bus; the future's result is the reply
        dict. Refusals come back as an already finished future."""
        try:
            return self._command(device, payload, decode_object(payload))
        except BusgateError as exc:
            return _finished(error_reply(exc))

    def _command(self, device: str, payload: bytes, fields: dict[str, Any]) -> Future:
        runner, driver = self._device(device)
        op, client = fields.get("op"), fields.get("client")
        if op in ("claim", "release"):
            return _finished(self._claim_op(device, fields))
        try:  # validated from the JSON text: strict JSON mode takes "velocity" for an enum
            command = driver.commands.validate_json(payload)
        except ValidationError as exc:
            raise refusal(exc) from exc
        if op not in UNCLAIMED_OPS:
            self.claims.check(device, client, self.clock())
        if driver.kind == "zlac706" and op == "velocity" and client:
            self._speed_clients[device] = client
        return _mapped(runner.submit(device, command))

    def _claim_op(self, device: str, fields: dict[str, Any]) -> dict[str, Any]:
        try:
            request = (Claim if fields.get("op") == "claim" else Release).model_validate(fields)
        except ValidationError as exc:
            raise refusal(exc) from exc
        now = self.clock()
        if isinstance(request, Claim):
            self.claims.claim(device, request.client, request.ttl_s, now)
            self._event(device, "claimed", client=request.client, ttl_s=request.ttl_s)
            return ok_reply(claimed_by=request.client, expires_in_s=request.ttl_s)
        self.claims.release(device, request.client, now)
        self._event(device, "released", client=request.client)
        return ok_reply(released=True)

    def follow(self, device: str, payload: bytes) -> dict[str, Any] | None:
        """A follow stream's new target; ``None`` when taken, else the error reply."""
        try:
            runner, driver = self._device(device)
            fields = decode_object(payload)
            client = fields.pop("client", None)
            if client is not None:
                self.claims.check(device, client, self.clock())
                self._stream_clients[device] = client
            else:
                self.claims.check(device, None, self.clock())
            try:
                target = driver.follow_target(fields)
            except CommandError as exc:
                raise refusal(exc) from exc
            runner.follow(device, target)
            return None
        except BusgateError as exc:
            return error_reply(exc)

    def estop(self) -> list[Future]:
        """Stop every device of the gateway, ahead of everything; never refused."""
        return [runner.estop() for runner in self.runners.values()]

    def bus_command(self, bus: str, payload: bytes) -> Future:
        """``group_move`` or ``scan`` on one bus."""
        try:
            runner = self.runners.get(bus)
            if runner is None:
                raise ApiError("unknown_bus", f"no bus {bus!r} on gateway {self.name}")
            fields = decode_object(payload)
            handlers = {"group_move": self._group_move, "scan": self._scan}
            handler = handlers.get(fields.get("op"))
            if handler is None:
                raise ApiError("bad_command", "bus ops are group_move and scan")
            return handler(runner, fields)
        except BusgateError as exc:
            return _finished(error_reply(exc))

    def _group_move(self, runner: BusRunner, fields: dict[str, Any]) -> Future:
        try:
            request = BusGroupMove.model_validate(fields)
        except ValidationError as exc:
            raise refusal(exc) from exc
        now = self.clock()
        for target in request.targets:
            if target.device not in runner.drivers:
                raise ApiError("unknown_device", f"no device {target.device!r} on this bus")
            self.claims.check(target.device, request.client, now)
        first, command = group_command(runner, request)
        return _mapped(runner.submit(first, command))

    def _scan(self, runner: BusRunner, fields: dict[str, Any]) -> Future:
        try:
            request = BusScan.model_validate(fields)
        except ValidationError as exc:
            raise refusal(exc) from exc
        protocol = runner.timing.protocol
        scanning = runner.scan(scan_requests(protocol, request.ids))
        answer: Future = Future()
        scanning.add_done_callback(lambda done: _settle(
            answer, done, lambda outcomes: ok_reply(found=scan_result(protocol, outcomes))))
        return answer

    # -- clients ----------------------------------------------------------------------------

    def client_left(self, client: str) -> None:
        """Deadman: the client's liveliness token went away."""
        for device in self.claims.drop_client(client):
            self._event(device, "released", client=client, reason="client gone")
        for device, owner in list(self._stream_clients.items()):
            if owner == client:
                del self._stream_clients[device]
                runner, _ = self.devices[device]
                runner.stop_stream(device, f"client {client} gone")
        for device, owner in list(self._speed_clients.items()):
            if owner == client:
                del self._speed_clients[device]
                runner, driver = self.devices[device]
                runner.submit(device, driver.parse('{"op":"velocity","rpm":0}'))
                self._event(device, "stopped", client=client, reason="client gone")

    # -- information ------------------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        return ok_reply(
            gateway=self.name,
            version=_version(),
            buses=[
                {"name": name, "protocol": runner.timing.protocol,
                 "devices": [{"name": device, "kind": driver.kind, "id": driver.device_id,
                              "state": runner.states.get(device)}
                             for device, driver in runner.drivers.items()]}
                for name, runner in self.runners.items()
            ],
        )

    def _device(self, device: str) -> tuple[BusRunner, Driver]:
        try:
            return self.devices[device]
        except KeyError:
            message = f"no device {device!r} on gateway {self.name}"
            raise ApiError("unknown_device", message) from None

    def _event(self, device: str, type_: str, **fields: Any) -> None:
        self.on_event(DeviceEvent(device, type_, fields))


def _finished(reply: dict[str, Any]) -> Future:
    future: Future = Future()
    future.set_result(reply)
    return future


def _mapped(submitted: Future) -> Future:
    """The runner's future (result dict, or a ``BusgateError``) as a reply envelope future."""
    answer: Future = Future()
    submitted.add_done_callback(lambda done: _settle(answer, done, lambda r: ok_reply(**r)))
    return answer


def _settle(answer: Future, done: Future, make: Callable[[Any], dict[str, Any]]) -> None:
    error = done.exception()
    answer.set_result(error_reply(error) if error is not None else make(done.result()))


def _version() -> str:
    try:
        return metadata.version("busgate")
    except metadata.PackageNotFoundError:
        return "unknown"


__all__ = ["MAX_PAYLOAD", "ApiError", "GatewayApi", "decode_object", "error_reply"]
