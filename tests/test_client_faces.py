"""The SDK's two faces are one surface: every public method of a class of the blocking face
(``busgate.client``) is a method of its asyncio twin (``busgate.client.aio``) with the same
parameters and result, a coroutine where the blocking one waits and an async generator where
it is a generator, or the very same method where neither waits. A method added to one face
alone, or given other parameters there, fails here; so does a face a type checker no longer
reads as it runs (a blocking ``Device`` where an asyncio one is meant, a coroutine not seen).
"""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import pytest

import busgate.client as bc

ROOT = Path(__file__).resolve().parent.parent
PAIRS = [
    (bc.Client, bc.aio.Client),
    (bc.Device, bc.aio.Device),
    (bc.Bus, bc.aio.Bus),
    (bc.Claim, bc.aio.Claim),
    (bc.Follow, bc.aio.Follow),
    (bc.Trajectory, bc.aio.Trajectory),
]
#: What a blocking face's method may be on the asyncio face.
TWINS = {
    "function": {"function", "coroutine"},
    "generator": {"async generator"},
    "property": {"property"},
}
#: The blocks each face enters and leaves (the client of the asyncio face is entered through
#: ``aio.connect``).
BLOCKS = [bc.Claim, bc.Follow, bc.Trajectory]


def public(cls: type) -> set[str]:
    return {name for name in dir(cls) if not name.startswith("_")}


def kind(attribute: object) -> str:
    if isinstance(attribute, property):
        return "property"
    if inspect.isasyncgenfunction(attribute):
        return "async generator"
    if inspect.iscoroutinefunction(attribute):
        return "coroutine"
    return "generator" if inspect.isgeneratorfunction(attribute) else "function"


def function_of(attribute: object) -> object:
    return attribute.fget if isinstance(attribute, property) else attribute


@pytest.mark.parametrize(("blocking", "awaiting"), PAIRS, ids=lambda cls: cls.__qualname__)
def test_each_public_method_of_one_face_is_the_other_faces_with_the_same_signature(
    blocking: type, awaiting: type
) -> None:
    assert public(blocking) == public(awaiting)
    for name in sorted(public(blocking)):
        mine = inspect.getattr_static(blocking, name)
        twin = inspect.getattr_static(awaiting, name)
        assert kind(twin) in TWINS[kind(mine)], f"{awaiting.__qualname__}.{name}: {kind(twin)}"
        if kind(twin) == "function":  # neither waits: the one method both faces share
            assert function_of(twin) is function_of(mine), f"{awaiting.__qualname__}.{name}"
        signature = inspect.signature(function_of(mine))  # type: ignore[arg-type]
        twins = inspect.signature(function_of(twin))  # type: ignore[arg-type]
        assert twins.parameters == signature.parameters, name
        async_ = "Async" if kind(twin) == "async generator" else ""  # Iterator: AsyncIterator
        assert twins.return_annotation == async_ + signature.return_annotation, name
        assert inspect.getdoc(function_of(twin)), f"{awaiting.__qualname__}.{name}: no docstring"


@pytest.mark.parametrize("blocking", BLOCKS, ids=lambda cls: cls.__qualname__)
def test_a_block_is_entered_and_left_with_the_same_signature_on_each_face(blocking) -> None:
    awaiting = getattr(bc.aio, blocking.__name__)
    for enter, aenter in (("__enter__", "__aenter__"), ("__exit__", "__aexit__")):
        assert kind(getattr(awaiting, aenter)) == "coroutine"
        assert inspect.signature(getattr(awaiting, aenter)) == inspect.signature(
            getattr(blocking, enter)
        )


def test_connect_takes_the_same_options_on_each_face() -> None:
    blocking, awaiting = inspect.signature(bc.connect), inspect.signature(bc.aio.connect)
    assert blocking.parameters == awaiting.parameters
    assert blocking.return_annotation == "Client"
    with pytest.raises(TypeError):
        bc.aio.connect(client_id="x", lease=1.0)  # a wrong option fails at once, unawaited


#: A program of each face, and what a type checker must read in it: ``reveal_type`` lines
#: name the type they must reveal, other marked lines the error they must raise.
PROGRAM = """\
from typing import Any
import busgate.client as bc

def blocking(c: bc.Client) -> None:
    device = c.device("la1")
    reveal_type(device)  # busgate.client.sync.Device
    reveal_type(device.move(100))  # dict[str, Any]
    reveal_type(device.states())  # typing.Iterator[Any]
    with device.claim(ttl_s=2.0) as claim, device.follow() as follow:
        reveal_type(claim)  # busgate.client.sync.Claim
        follow.set(position=3)
    reveal_type(c.play(["la1"], []).feedback())  # typing.Iterator[dict[str, Any]]
    reveal_type(c.bus("uart0").scan())  # list[Any]
    c.device(1)  # error: arg-type


async def awaiting(c: bc.aio.Client) -> None:
    device = await c.device("la1")
    reveal_type(device)  # busgate.client.aio.Device
    reveal_type(await device.move(100))  # dict[str, Any]
    reveal_type(device.states())  # typing.AsyncIterator[Any]
    async with device.claim(ttl_s=2.0) as claim:
        reveal_type(claim)  # busgate.client.aio.Claim
    reveal_type(await c.gateways())  # dict[str, busgate.schemas.api.InfoReply]
    device.move(1)  # error: unused-coroutine
    async with bc.aio.connect(client_id="x") as opened:
        reveal_type(opened)  # busgate.client.aio.Client
    bc.aio.connect(client_id=3)  # error: arg-type
"""


def test_a_type_checker_reads_each_face_as_it_runs(tmp_path: Path) -> None:
    program = tmp_path / "program.py"
    program.write_text(PROGRAM)
    checked = subprocess.run(
        [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"),
         "--cache-dir", str(tmp_path / "cache"), "--show-error-codes", "--no-pretty",
         str(program)],
        cwd=ROOT / "tools" / "typecheck", capture_output=True, text=True, check=False,
    )  # fmt: skip
    said: dict[int, list[str]] = {}
    for line in checked.stdout.splitlines():
        where, _, what = line.partition(": ")
        if where.startswith(str(program)) and not what.startswith("note: Are you missing"):
            said.setdefault(int(where.rsplit(":", 1)[1]), []).append(what)
    expected: dict[int, list[str]] = {}
    for number, line in enumerate(PROGRAM.splitlines(), 1):
        code, _, mark = line.partition("  # ")
        if code.strip().startswith("reveal_type("):
            expected[number] = [f'note: Revealed type is "{mark}"']
        elif mark.startswith("error: "):
            expected[number] = [mark]
    found = {n: [w if w.startswith("note") else f"error: {w.rsplit('[', 1)[1][:-1]}"
                 for w in what] for n, what in said.items()}  # fmt: skip
    assert found == expected, checked.stdout
