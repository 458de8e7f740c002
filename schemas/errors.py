"""Turning a JSON text into a command model, with one readable line when it is refused.

Pydantic's ``ValidationError`` becomes a ``CommandError`` raised from it, whose message names
every offending field, so the CLI and the zenoh API report the same words. The code a reply
gives it is the ``ValidationError``'s: ``out_of_range`` when only values were outside their
bounds, else ``bad_command`` (``busgate.gateway.api.errors``).
"""

from __future__ import annotations

from typing import Any

from pydantic import TypeAdapter, ValidationError

from busgate.codecs.errors import CommandError


def command_from_json(adapter: TypeAdapter[Any], text: str | bytes) -> Any:
    """Validate ``text`` as a command; raise ``CommandError`` with a one-line reason."""
    try:
        return adapter.validate_json(text)
    except ValidationError as exc:
        raise CommandError(f"invalid command: {describe_validation_error(exc)}") from exc


def describe_validation_error(exc: ValidationError) -> str:
    """``position: Input should be less than or equal to 2000; …`` on one line."""
    parts = []
    for error in exc.errors(include_url=False):
        location = ".".join(str(p) for p in error["loc"])
        parts.append(f"{location}: {error['msg']}" if location else error["msg"])
    return "; ".join(parts)
