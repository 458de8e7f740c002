"""The API boundary's one mapping from an exception to the error code its reply carries.

Every path ends here, whichever thread the exception was raised on: a payload refused in a
zenoh callback, a command refused while the bus thread planned it (an encode error, the
authority, a driver's state rule), a job that failed on the wire. Nothing before it turns one
exception into another to get a code. Rules:

1. One of busgate's own errors carries its class's code (``busgate.errors``; a
   ``RefusedError`` names its own). An ``EncodeError`` is ``out_of_range`` wherever it arose.
2. A schema's refusal (pydantic's ``ValidationError``, or the one-line ``CommandError`` made
   from it) is ``out_of_range`` when every problem is a value outside its bounds, a codec's
   ``EncodeError`` raised by a validator included, and ``bad_command`` otherwise.
3. Anything else is a bug: ``internal`` (its traceback is logged where it was caught).
"""

from __future__ import annotations

import logging
from typing import Any

from pydantic import ValidationError

from busgate.errors import BusgateError, CommandError
from busgate.schemas.api import MAX_MESSAGE
from busgate.schemas.validation import cut, describe_validation_error, refusal_code

#: What a client's request may be refused with (rules 1 and 2), as opposed to a bug.
REFUSALS = (BusgateError, ValidationError)


def error_code(exc: BaseException) -> str:
    """The code of ``exc`` in a reply."""
    refused = _schema_refusal(exc)
    if refused is not None:
        return refusal_code(refused)
    return exc.code if isinstance(exc, BusgateError) else "internal"


def error_reply(exc: BaseException) -> dict[str, Any]:
    """The error envelope for ``exc``: its code, and a message for people, cut to the
    longest a reply carries (``MAX_MESSAGE``: every problem of a long command is more)."""
    if isinstance(exc, ValidationError):
        message = f"invalid command: {describe_validation_error(exc)}"
    else:
        message = str(exc) or type(exc).__name__
    return {
        "ok": False,
        "error": {"code": error_code(exc), "message": cut(message, MAX_MESSAGE - 1)},
    }


def failure_reply(exc: Exception, log: logging.Logger, what: str) -> dict[str, Any]:
    """The error reply of what a request's handling raised (called in its ``except``): a
    refusal as its code, anything else ``internal`` with its traceback logged as ``what``
    failed (rule 3): every request gets one answer, whatever happens."""
    if not isinstance(exc, REFUSALS):
        log.exception("%s failed", what)
    return error_reply(exc)


def _schema_refusal(exc: BaseException) -> ValidationError | None:
    """The schema's refusal ``exc`` is (rule 2), if it is one."""
    if isinstance(exc, ValidationError):
        return exc
    if isinstance(exc, CommandError) and isinstance(exc.__cause__, ValidationError):
        return exc.__cause__
    return None
