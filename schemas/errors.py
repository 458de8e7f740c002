"""Turning a JSON text into a command model, with one readable line when it is refused.

Pydantic's ``ValidationError`` becomes a ``CommandError`` raised from it, whose message names
every offending field, so the CLI and the zenoh API report the same words. The code a reply
gives it is the ``ValidationError``'s (``refusal_code``): ``out_of_range`` when only values
were outside their bounds, else ``bad_command``; the gateway's replies
(``busgate.gateway.api.errors``) and the client's own checks (``busgate.client``) both ask it.
"""

from __future__ import annotations

from typing import Any

from pydantic import TypeAdapter, ValidationError

from busgate.codecs.errors import CommandError, EncodeError

#: Pydantic error types that mean "a value outside its range".
RANGE_ERRORS = frozenset(
    {
        "less_than",
        "less_than_equal",
        "greater_than",
        "greater_than_equal",
        "multiple_of",
        "too_short",
        "too_long",
    }
)


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


def refusal_code(exc: ValidationError) -> str:
    """``out_of_range`` when every problem is a value outside its bounds (a codec's
    ``EncodeError`` raised by a validator included), ``bad_command`` otherwise."""
    problems = exc.errors()
    in_range = bool(problems) and all(
        problem["type"] in RANGE_ERRORS
        or isinstance(problem.get("ctx", {}).get("error"), EncodeError)
        for problem in problems
    )
    return "out_of_range" if in_range else "bad_command"
