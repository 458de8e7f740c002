"""Turning a JSON text into a command model, with one readable line when it is refused.

Pydantic's ``ValidationError`` becomes a ``CommandError`` raised from it, whose message names
every offending field, so the CLI and the zenoh API report the same words. An op the family
does not have is told in one line of its own: for an op another family has (``disable`` to an
LA), what does its deed in this one (the family schema's ``OPS_ELSEWHERE``); else the op it
most likely misspells (``suggestion``, which also serves the config's unknown keys), never one
that undoes what was asked (``enable`` for ``disable``). The code a reply gives it is the
``ValidationError``'s (``refusal_code``): ``out_of_range`` when only values were outside their
bounds, else ``bad_command``; the gateway's replies (``busgate.schemas.replies``) and the
client's own checks (``busgate.client``) both ask it.
"""

from __future__ import annotations

import difflib
import json
import re
from collections.abc import Callable, Sequence
from typing import Any

from pydantic import BaseModel, TypeAdapter, ValidationError

from busgate.codecs.errors import EncodeError
from busgate.errors import CommandError
from busgate.schemas.families import FAMILIES

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


#: How much of an unknown op a refusal repeats (a peer may send 64 KiB of one).
SHOWN_OP_CHARS = 40
#: How much of a name a refusal repeats (a key may carry 60,000 characters of one).
SHOWN_NAME_CHARS = 64
#: Words a suggestion never puts for each other: each undoes what the other does.
OPPOSITES = frozenset({frozenset({"enable", "disable"})})
#: A quoted tag in pydantic's ``expected_tags`` (``'move', 'follow'``).
_QUOTED_TAG = re.compile(r"'([^']*)'")


def command_from_json(adapter: TypeAdapter[Any], text: str | bytes, family: str) -> Any:
    """Validate ``text`` as one of ``family``'s commands; raise ``CommandError`` with a
    one-line reason (``describe_command_error``)."""
    return _command(adapter.validate_json, text, family)


def command_from_object(adapter: TypeAdapter[Any], fields: Any, family: str) -> Any:
    """``command_from_json`` for a JSON object already parsed."""
    return _command(adapter.validate_python, fields, family)


def follow_target_from(model: type[BaseModel], payload: Any) -> Any:
    """``payload`` (a follow put's object) as ``model``; ``CommandError`` saying ``invalid
    follow target:`` and every problem when it is not one."""
    try:
        return model.model_validate(payload)
    except ValidationError as exc:
        raise CommandError(f"invalid follow target: {describe_validation_error(exc)}") from exc


def _command(validate: Callable[[Any], Any], value: Any, family: str) -> Any:
    try:
        return validate(value)
    except ValidationError as exc:
        raise CommandError(describe_command_error(exc, family)) from exc


def describe_command_error(exc: ValidationError, family: str) -> str:
    """``unknown op `mvoe` for inspire_la (did you mean `move`?)`` when the command's op is
    none of the family's (every op it has when none is close), ``missing `op` …`` when it has
    none; else ``invalid command: `` and every problem (``describe_validation_error``)."""
    errors = exc.errors(include_url=False)
    if len(errors) == 1 and errors[0]["type"] == "union_tag_not_found" and not errors[0]["loc"]:
        field = errors[0]["ctx"]["discriminator"].strip("'")
        return f"missing `{field}`: every {family} command names its {field}"
    if len(errors) == 1 and errors[0]["type"] == "union_tag_invalid" and not errors[0]["loc"]:
        op, expected = errors[0]["ctx"]["tag"], errors[0]["ctx"]["expected_tags"]
        field = errors[0]["ctx"]["discriminator"].strip("'")
        given = errors[0]["input"].get(field) if isinstance(errors[0]["input"], dict) else op
        if not isinstance(given, str):  # its tag is Python's repr: `None`, `7`
            return f"`{field}` is a string naming the command, not {json.dumps(given)[:40]}"
        named = shown(op, SHOWN_OP_CHARS)
        if instead := _ops_elsewhere(family).get(op):
            return f"unknown op `{named}` for {family}: {instead}"
        return f"unknown op `{named}` for {family}{suggestion(op, _QUOTED_TAG.findall(expected))}"
    return f"invalid command: {describe_validation_error(exc)}"


def suggestion(word: str, choices: Sequence[str], *, listed: int | None = None) -> str:
    """What follows a ``word`` that is none of ``choices``: `` (did you mean `move`?)`` for the
    one it most likely misspells (``closest``); else the choices, when there are at most
    ``listed`` of them (``None``: however many), or nothing."""
    meant = closest(word, choices)
    if meant is not None and frozenset({word, meant}) not in OPPOSITES:
        return f" (did you mean `{meant}`?)"
    if listed is None or len(choices) <= listed:
        return f" (allowed: {', '.join(f'`{choice}`' for choice in choices)})"
    return ""


def _ops_elsewhere(family: str) -> dict[str, str]:
    """What does another family's op in ``family`` (its schema's ``OPS_ELSEWHERE``)."""
    entry = FAMILIES.get(family)
    return {} if entry is None else getattr(entry.schema, "OPS_ELSEWHERE", {})


def closest(word: str, choices: Sequence[str]) -> str | None:
    """The choice ``word`` most likely misspells (``difflib``'s ratio 0.6 or more), if any."""
    matches = difflib.get_close_matches(word, choices, n=1)
    return matches[0] if matches else None


def likeliest(word: str, choices: Sequence[str]) -> list[str]:
    """Every choice ``word`` most likely misspells, in order: those as close as ``closest``'s,
    whose pick among them would be a guess (``lal``: ``la1``, ``la2`` and ``la3`` alike)."""
    scores = {c: difflib.SequenceMatcher(None, word, c).ratio() for c in choices}
    best = max(scores.values(), default=0.0)
    return sorted(c for c, score in scores.items() if score == best) if best >= 0.6 else []


def describe_validation_error(exc: ValidationError) -> str:
    """``position: must be at most 2000, not 2500; …`` on one line: a number past a bound
    with the bound and the number (``_past_bound``), any other problem in pydantic's words."""
    parts = []
    for error in exc.errors(include_url=False):
        location = ".".join(str(p) for p in error["loc"])
        message = _past_bound(error) or _plain(error)
        parts.append(f"{location}: {message}" if location else message)
    return "; ".join(parts)


def _plain(error: Any) -> str:
    """pydantic's words for ``error``, but for those in its own terms: a validator's own
    message without "Value error, ", and a command's missing or unknown op said as such."""
    kind, context = error["type"], error.get("ctx", {})
    if kind == "union_tag_not_found":
        return f'no {context["discriminator"]}: a command names what it is ({{"op": …}})'
    if kind == "union_tag_invalid":
        tag = cut(repr(context["tag"]), SHOWN_OP_CHARS)
        return f"unknown {context['discriminator']} {tag}: one of {context['expected_tags']}"
    return message_of(error)


def message_of(error: Any) -> str:
    """pydantic's message for ``error``; a validator's own as it wrote it, without the
    "Value error, " pydantic puts before it."""
    return str(error["msg"]).removeprefix("Value error, ")


#: How a number past each of pydantic's bounds is told, by the bound's error type.
_BOUNDS = {
    "less_than_equal": ("le", "at most"),
    "less_than": ("lt", "below"),
    "greater_than_equal": ("ge", "at least"),
    "greater_than": ("gt", "above"),
}


def _past_bound(error: Any) -> str | None:
    """``must be at most 2000, not 2500`` for a number past a bound; ``None`` for anything
    else. The number as sent, cut (a peer may send a thousand digits)."""
    bound = _BOUNDS.get(error["type"])
    value = error.get("input")
    if bound is None or isinstance(value, bool) or not isinstance(value, int | float):
        return None
    key, words = bound
    limit = error["ctx"][key]
    shown_limit = f"{limit:.15g}" if isinstance(limit, float) else limit  # 1000, not 1000.0
    return f"must be {words} {shown_limit}, not {cut(repr(value), SHOWN_OP_CHARS)}"


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


#: What a terminal takes for an order rather than text: C0 and C1 controls (an escape starts
#: with one), and the marks that reorder or hide what follows them; and the same but for the
#: line ends of text laid out in lines.
_MARKS = "\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069"
_NOT_TEXT = re.compile(f"[\x00-\x1f{_MARKS}]")
_NOT_TEXT_IN_LINES = re.compile(f"[\x00-\x09\x0b-\x1f{_MARKS}]")


def printable(text: str, most: int | None = None, *, lines: bool = False) -> str:
    r"""``text`` as a terminal may show it, whoever wrote it: each control or reordering mark
    as its ``\uXXXX`` (a JSON escape too), line ends too unless ``lines``, the rest as it
    is; cut to ``most`` characters (``…``) when given.

    >>> printable("ok \x1b[2J\u202eok"), printable("1–254 é", 5), printable("a\nb", lines=True)
    ('ok \\u001b[2J\\u202eok', '1–254…', 'a\nb')
    """
    pattern = _NOT_TEXT_IN_LINES if lines else _NOT_TEXT
    kept = text if most is None else cut(text, most)
    return pattern.sub(lambda found: f"\\u{ord(found.group()):04x}", kept)


def shown(text: str, most: int = SHOWN_NAME_CHARS) -> str:
    """``text`` as a refusal repeats it: cut to ``most`` characters (``…``), its control
    characters and reordering marks escaped (``printable``), any other letter as it is (``ü``,
    not ``\\xfc``, which the reply's JSON escaped again)."""
    return printable(text, most)


def cut(text: str, most: int) -> str:
    """``text``, or its first ``most`` characters and ``…`` when it is longer.

    >>> cut("abcdef", 3), cut("ok", 3)
    ('abc…', 'ok')
    """
    return text if len(text) <= most else text[:most] + "…"
