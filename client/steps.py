"""How one operation serves both faces of the SDK: as a generator of the steps it waits for.

Each method that waits is written once (``surface.py``, ``devices.py``,
``trajectories.Handle``) as a generator that yields what it waits for: ``Wait`` (the future of
an exchange, within its timeout), ``Next`` (the next item of a feed, ``None`` at its timeout)
and ``Call`` (a call that blocks: opening and closing the session). It returns its result; a
feed (``Device.states``, ``Trajectory.feedback``) yields its items between its steps. A face
runs the generator: the blocking face waits for each step (``run``), the asyncio face awaits
it (``arun``); either hands the step's result back to the generator, or its failure, raised
where it waited, so that what an operation does on failure (a claim given back) is written
once too. ``faces.py`` makes such a generator a method of both faces.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import AsyncGenerator, Callable, Generator
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

from busgate.client.errors import NoAnswerError

#: How often an awaiter that left looks whether its call has ended (``Call.left_wait_s``).
LEFT_POLL_S = 0.01

R = TypeVar("R")
T = TypeVar("T")

#: What a wait adds to the timeout zenoh was given before it says nobody answered (zenoh
#: settles a query at its timeout; this covers a late settle on a loaded host).
WAIT_MARGIN_S = 1.0


class Step:
    """What an operation waits for: ``wait`` blocks until it is there, ``awaited`` awaits it."""

    __slots__ = ()

    def wait(self) -> Any:
        raise NotImplementedError

    async def awaited(self) -> Any:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class Wait(Step):
    """The result of ``future`` (its exception raised), within ``timeout_s`` plus ``margin_s``,
    the margin zenoh may take to settle a query (none for a future settled here, as a
    trajectory's result); else ``NoAnswerError`` naming ``what`` (the future is cancelled)."""

    future: Future
    timeout_s: float
    what: str
    margin_s: float = WAIT_MARGIN_S

    def wait(self) -> Any:
        try:
            return self.future.result(self.timeout_s + self.margin_s)
        except TimeoutError:
            if self.future.done():  # its own (a NoAnswerError is a TimeoutError too), or it
                return self.future.result(0)  # came just as the wait ended
            self.future.cancel()
            raise self._no_answer() from None

    async def awaited(self) -> Any:
        came = asyncio.wrap_future(self.future)  # settled on the loop, cancelled with it
        try:
            return await asyncio.wait_for(came, self.timeout_s + self.margin_s)
        except TimeoutError:
            if came.done() and not came.cancelled():  # its own error, or late: as in ``wait``
                return came.result()
            raise self._no_answer() from None

    def _no_answer(self) -> NoAnswerError:
        return NoAnswerError(f"{self.what}: no answer within {self.timeout_s:.4g} s")


@dataclass(frozen=True, slots=True)
class Next(Step):
    """The result of ``future``, or ``None`` when it did not come within ``timeout_s`` (the
    future is cancelled): the next item of something that ends at its timeout."""

    future: Future
    timeout_s: float

    def wait(self) -> Any:
        try:
            return self.future.result(self.timeout_s)
        except TimeoutError:
            self.future.cancel()
            return None

    async def awaited(self) -> Any:
        try:
            return await asyncio.wait_for(asyncio.wrap_future(self.future), self.timeout_s)
        except TimeoutError:
            return None


@dataclass(frozen=True, slots=True)
class Call(Step):
    """``function()``, a call that blocks: made as it is by the blocking face, on a daemon
    thread of its own by the asyncio face (the loop never blocks). Not asyncio's executor,
    whose threads the interpreter's exit waits for: a program that stopped waiting for a
    session's opening (a Ctrl-C, a stop signal) waited at its exit until zenoh gave up on an
    endpoint that never answered, 10 s."""

    function: Callable[[], Any]
    #: What is done with a result whose awaiter left (cancelled) before it came: a session
    #: opened for nobody is closed (core rule 7), as the blocking face's is.
    unwanted: Callable[[Any], None] | None = None
    #: How long an awaiter that leaves waits at most for the call, and ``unwanted``, to end
    #: first, as the blocking face's caller does (core rule 7): a program that ended at once
    #: after a connect's deadline aborted ("FATAL: exception not rethrown", an audit: 4 runs
    #: in 5) when zenoh handed the session's thread back as the interpreter finalized.
    left_wait_s: float = 0.0

    def wait(self) -> Any:
        return self.function()

    async def awaited(self) -> Any:
        loop = asyncio.get_running_loop()
        called: asyncio.Future[Any] = loop.create_future()
        unwanted = self.unwanted
        ended = threading.Event()  # the call, and what was done with its unwanted result

        def dispose(result: Any, error: BaseException | None) -> None:
            try:
                if error is None and unwanted is not None:
                    unwanted(result)
            finally:
                ended.set()

        def settle(result: Any, error: BaseException | None) -> None:
            if called.cancelled():
                threading.Thread(target=dispose, args=(result, error), daemon=True).start()
                return
            ended.set()
            if error is None:
                called.set_result(result)
            else:
                called.set_exception(error)

        def call() -> None:
            result, error = None, None
            try:
                result = self.function()
            except BaseException as exc:  # raised where it is awaited
                error = exc
            try:
                loop.call_soon_threadsafe(settle, result, error)
            except RuntimeError:  # the loop ended first: nobody awaits it
                dispose(result, error)

        threading.Thread(target=call, name="busgate-call", daemon=True).start()
        try:
            return await called
        except asyncio.CancelledError:
            if called.done() and not called.cancelled() and called.exception() is None:
                ended.clear()  # its result came as the awaiter was cancelled: nobody takes it
                threading.Thread(target=dispose, args=(called.result(), None), daemon=True).start()
            deadline = loop.time() + self.left_wait_s
            while not ended.is_set() and loop.time() < deadline:
                await asyncio.sleep(LEFT_POLL_S)
            raise


#: An operation: the steps it waits for, then its result.
Steps = Generator[Step, Any, R]
#: A feed: its items as they come, and the steps it waits for between them.
Items = Generator[Step | T, Any, None]


class _Run:
    """One run of a generator of steps: a context manager (that closes the generator), and an
    iterator of its steps and items. What a step gave (``waited``, ``awaited``), or its
    failure, is handed back to the generator as it asks for the next; ``result`` is what it
    returned."""

    def __init__(self, steps: Generator[Any, Any, Any]) -> None:
        self._steps = steps
        self._took: tuple[Any, BaseException | None] = (None, None)
        self.result: Any = None

    def __enter__(self) -> _Run:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._steps.close()

    def __iter__(self) -> _Run:
        return self

    def __next__(self) -> Any:
        (value, error), self._took = self._took, (None, None)
        try:
            return self._steps.send(value) if error is None else self._steps.throw(error)
        except StopIteration as stop:
            self.result = stop.value
            raise StopIteration from None

    def waited(self, step: Step) -> None:
        try:
            self._took = (step.wait(), None)
        except BaseException as exc:  # raised in the generator, where it waited
            self._took = (None, exc)

    async def awaited(self, step: Step) -> None:
        try:
            self._took = (await step.awaited(), None)
        except BaseException as exc:  # a cancel too: the generator gives back what it took
            self._took = (None, exc)


def driven(steps: Generator[Any, Any, R]) -> Generator[Any, None, R]:
    """The blocking face's run of ``steps``: each step waited for, each item passed on; then
    its result."""
    with _Run(steps) as running:
        for step in running:
            if isinstance(step, Step):
                running.waited(step)
            else:
                yield step
    return running.result


async def adriven(
    steps: Generator[Any, Any, Any], done: Callable[[Any], object] | None = None
) -> AsyncGenerator[Any, None]:
    """The asyncio face's run of ``steps``: each step awaited, each item passed on; then its
    result to ``done``."""
    with _Run(steps) as running:
        for step in running:
            if isinstance(step, Step):
                await running.awaited(step)
            else:
                yield step
    if done is not None:
        done(running.result)


def run(steps: Steps[R]) -> R:
    """The result of ``steps``, each step waited for (the blocking face)."""
    items = driven(steps)
    try:
        item = next(items)
    except StopIteration as stop:
        return stop.value
    items.close()
    raise TypeError(f"an operation yielded {item!r}, not a step")


async def arun(steps: Steps[R]) -> R:
    """The result of ``steps``, each step awaited (the asyncio face)."""
    result: list[R] = []
    async with contextlib.aclosing(adriven(steps, result.append)) as items:
        async for item in items:
            raise TypeError(f"an operation yielded {item!r}, not a step")
    return result[0]
