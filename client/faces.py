"""How an operation of the SDK becomes a method of both faces.

``@waiting`` (an operation that returns a result) and ``@feeding`` (one that yields items as
they come) make a generator of steps (``steps.py``) an ``Operation``: a class of the blocking
face (``Blocking``) has it as a method that waits (a generator, for a feed), a class of the
asyncio face (``Awaiting``) as a coroutine (an async generator), each with the operation's
parameters, docstring and result. Type checkers read each face's method from the
descriptor's ``__get__``, overloaded on the face of the instance; at run time each face's
class gets real functions when it is made (``Face.__init_subclass__``), so ``inspect``,
``help`` and every call see plain methods, no descriptor on the way.
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from typing import Any, ClassVar, Concatenate, Generic, ParamSpec, TypeVar, overload

from busgate.client.steps import Items, Steps, adriven, arun, driven, run

P = ParamSpec("P")
R = TypeVar("R")
S = TypeVar("S")
T = TypeVar("T")
#: What a method of the blocking face gives, and one of the asyncio face.
B = TypeVar("B")
A = TypeVar("A")


def _waits(steps: Callable[..., Steps[Any]]) -> Callable[..., Any]:
    def method(face: Any, *args: Any, **kwargs: Any) -> Any:
        return run(steps(face, *args, **kwargs))

    return method


def _awaits(steps: Callable[..., Steps[Any]]) -> Callable[..., Any]:
    async def method(face: Any, *args: Any, **kwargs: Any) -> Any:
        return await arun(steps(face, *args, **kwargs))

    return method


def _iterates(steps: Callable[..., Items[Any]]) -> Callable[..., Any]:
    def method(face: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
        yield from driven(steps(face, *args, **kwargs))

    return method


def _aiterates(steps: Callable[..., Items[Any]]) -> Callable[..., Any]:
    async def method(face: Any, *args: Any, **kwargs: Any) -> AsyncIterator[Any]:
        async with contextlib.aclosing(adriven(steps(face, *args, **kwargs))) as items:
            async for item in items:
                yield item

    return method


class Operation(Generic[P, B, A]):
    """A generator of steps as a method of both faces: ``makers`` make the blocking and the
    asyncio face's method of it, whose results ``returns`` names (``{}``: what the generator
    returns)."""

    def __init__(
        self,
        steps: Callable[..., Any],
        makers: tuple[Callable[[Any], Callable[..., Any]], Callable[[Any], Callable[..., Any]]],
        returns: tuple[str, str],
    ) -> None:
        self.steps, self._makers, self._returns = steps, makers, returns

    @overload
    def __get__(self, face: Blocking, owner: type | None = None) -> Callable[P, B]: ...
    @overload
    def __get__(self, face: Awaiting, owner: type | None = None) -> Callable[P, A]: ...
    @overload
    def __get__(self, face: object, owner: type | None = None) -> Operation[P, B, A]: ...
    def __get__(self, face: object, owner: type | None = None) -> Any:
        return self  # reached only through a class both faces share

    def method_of(self, face: type[Face]) -> Callable[..., Any]:
        """This operation as a method of ``face``, a class of one face."""
        awaits = bool(face._awaits)
        method = self._makers[awaits](self.steps)
        _signed(method, self.steps, face.__module__, self._returns[awaits])
        method.__qualname__ = f"{face.__qualname__}.{method.__name__}"
        return method


def waiting(
    steps: Callable[Concatenate[Any, P], Steps[R]],
) -> Operation[P, R, Coroutine[Any, Any, R]]:
    """``@waiting``: an operation as a method that waits for its result (the blocking face)
    or a coroutine (the asyncio face)."""
    return Operation(steps, (_waits, _awaits), ("{}", "{}"))


def feeding(
    steps: Callable[Concatenate[Any, P], Items[T]],
) -> Operation[P, Iterator[T], AsyncIterator[T]]:
    """``@feeding``: a feed as a generator of its items (the blocking face) or an async
    generator (the asyncio face)."""
    return Operation(steps, (_iterates, _aiterates), ("Iterator[{}]", "AsyncIterator[{}]"))


class Face:
    """A class of the SDK's surface. One that both faces share holds operations; a class of
    one face (``Blocking``, ``Awaiting``) gets each of them as a method of its face when it is
    made."""

    #: Set by each face: whether its methods await (``None``: a class both faces share), what
    #: its ``repr`` puts before a class's name, and the block its context managers open.
    _awaits: ClassVar[bool | None] = None
    _prefix: ClassVar[str] = ""
    _block: ClassVar[str] = "with"

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls._awaits is None:
            return
        for name in dir(cls):
            operation = inspect.getattr_static(cls, name)
            if isinstance(operation, Operation):
                setattr(cls, name, operation.method_of(cls))


class Blocking(Face):
    """The classes of the blocking face (``busgate.client``): their methods wait."""

    _awaits = False


class Awaiting(Face):
    """The classes of the asyncio face (``busgate.client.aio``): their methods are coroutines."""

    _awaits = True
    _prefix = "aio."
    _block = "async with"


def _signed(function: Any, steps: Callable[..., Any], module: str, returns: str) -> None:
    """``function`` named, documented and signed as ``steps``, in ``module``; ``returns`` is
    its result (``{}`` standing for what ``steps`` returns)."""
    signature = inspect.signature(steps)
    result = str(signature.return_annotation)  # a string: "Steps[…]" or "Items[…]"
    result = returns.format(result[result.index("[") + 1 : -1])
    function.__name__, function.__module__ = steps.__name__, module
    function.__doc__ = steps.__doc__
    function.__annotations__ = {**_annotations(signature), "return": result}
    function.__signature__ = signature.replace(return_annotation=result)
    function.__wrapped__ = steps


def _annotations(signature: inspect.Signature) -> dict[str, Any]:
    return {
        name: parameter.annotation
        for name, parameter in signature.parameters.items()
        if parameter.annotation is not inspect.Parameter.empty
    }


def opener(steps: Callable[P, Steps[S]], face: Callable[[S], R]) -> Callable[P, R]:
    """The blocking face's ``connect``: its client (``face``) of what ``steps`` opened, with
    the parameters and docstring of ``steps``."""

    def connect(*args: P.args, **kwargs: P.kwargs) -> R:
        inspect.signature(steps).bind(*args, **kwargs)  # told as connect's, not Core's
        return face(run(steps(*args, **kwargs)))

    _signed(connect, steps, face.__module__, getattr(face, "__name__", "{}"))
    connect.__name__ = connect.__qualname__ = "connect"
    return connect


def taking(source: Callable[P, Any]) -> Callable[[Callable[..., R]], Callable[P, R]]:
    """A function that takes what ``source`` takes: its parameters, for type checkers and
    ``inspect`` alike (``connect`` takes what a client's session takes)."""

    def made(function: Callable[..., R]) -> Callable[P, R]:
        _take_parameters(function, source, [])
        return function

    return made


def init_taking(
    source: Callable[P, Any],
) -> Callable[[Callable[..., None]], Callable[Concatenate[Any, P], None]]:
    """An ``__init__`` that takes what ``source`` takes (the asyncio face's ``connect``, a
    class)."""

    def made(init: Callable[..., None]) -> Callable[Concatenate[Any, P], None]:
        self = inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD)
        _take_parameters(init, source, [self])
        return init

    return made


def _take_parameters(function: Any, source: Callable[..., Any], first: list[Any]) -> None:
    taken = inspect.signature(source)
    own = inspect.signature(function)
    signature = own.replace(parameters=[*first, *taken.parameters.values()])
    function.__signature__ = signature
    function.__annotations__ = {**_annotations(signature), "return": own.return_annotation}
