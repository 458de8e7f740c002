"""Where a job's outcome goes: the future its client waits on (a poll has none).

Its own module because a job's end is decided in several places of the bus thread (its last
reply, a failure for good, a deadline, an e-stop, a lost link, a full queue), and each must
answer the same way. Rules:

1. A future gets one outcome: the result (the replies' fields merged, with the device's
   state), the error that ended the job, or a refusal. One that has an outcome already, or
   was cancelled (its client was answered without it), is left alone.
2. A job whose future was cancelled before its first request went out is never sent.
3. An attempt that is tried again leaves nothing behind; a failure for good is the job's
   error; a scan records every probe's reply, or ``None``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from typing import Any

from busgate.errors import BusgateError, BusyError, RefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.scheduler.planner import Job

#: The device's state for a job's result (``None``: the job is for no one device).
StateOf = Callable[[str], dict[str, Any] | None]


def may_start(job: Job) -> bool:
    """Mark the job's future running; ``False`` when it was cancelled (rule 2)."""
    future = job.future
    return future is None or (not future.done() and future.set_running_or_notify_cancel())


def expired(job: Job, bus: str, start_s: float) -> BusyError:
    """The refusal of ``job``, dropped at its deadline: a command that found no room on the
    bus within ``start_s``, or a scan that found none for its last probes."""
    if job.scan:
        probed = len(job.outcomes or ())
        return BusyError(
            f"bus {bus}: the scan found no room to probe its last {len(job.requests)} ids "
            f"({probed} probed) before its deadline; nothing more was sent"
        )
    return BusyError(
        f"bus {bus}: the command found no room on the bus within {start_s:.0f} s and was "
        "dropped; nothing was sent"
    )


def record(
    job: Job, request: Request, reply: tuple[object, ...] | None, error: BaseException | None
) -> None:
    """What one attempt of ``request`` came to, once it will not be tried again (rule 3):
    ``reply`` the answer's events (``None``: it failed, with ``error``)."""
    if error is not None:
        job.error = error
    if job.outcomes is not None:
        job.outcomes.append((request, reply))


def result_of(job: Job, state_of: StateOf) -> dict[str, Any]:
    """The replies' fields merged, and the device's state."""
    merged: dict[str, Any] = {}
    for reply in job.replies:
        merged.update(reply)
    state = state_of(job.device)
    if state is not None:
        merged["state"] = state
    return merged


def complete(job: Job, state_of: StateOf) -> None:
    """The job is over: its outcome to its future (rule 1)."""
    future = job.future
    if future is None or future.done():
        return
    if job.outcomes is not None:
        settle(future, result=job.outcomes)
    elif job.error is not None and not job.keep_going:
        settle(future, error=job.error)
    else:
        settle(future, result=result_of(job, state_of))


def fail(job: Job, error: BusgateError) -> None:
    """The job ends with ``error`` (rule 1)."""
    if job.future is not None:
        settle(job.future, error=error)


def pass_on(source: Future, future: Future) -> None:
    """``future`` gets ``source``'s outcome once it has one (an e-stop that joined another)."""

    def passed(done: Future) -> None:
        error = done.exception()
        settle(future, result=None if error is not None else done.result(), error=error)

    source.add_done_callback(passed)


def cancelled_by_estop() -> RefusedError:
    """The refusal of a command that an e-stop came before: it is never carried out (a
    reset right after the e-stop would otherwise let it move the device)."""
    return RefusedError("estopped", "an e-stop cancelled it before it was carried out")


def settled(result: Any) -> Future:
    """A future that already has ``result``: an answer that needed no bus."""
    future: Future = Future()
    future.set_result(result)
    return future


def settle(future: Future, *, result: Any = None, error: BaseException | None = None) -> None:
    """Give ``future`` its outcome, unless it has one already or was cancelled (rule 1)."""
    with contextlib.suppress(InvalidStateError):
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
