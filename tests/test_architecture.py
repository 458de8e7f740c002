"""The rooms of the house and the arrows between them (docs/architecture.md): each package
imports only the ones below it. A new import against the arrows fails here, naming the file.

    codecs  <-  schemas  <-  gateway.drivers  <-  gateway.scheduler  <-  gateway.api
       ^           ^            |                                         ^
       +---- gateway.bus <------+                          gateway.service <- gateway.cli
                   |
                 client  (the SDK: codecs' errors and the schemas; the daemon uses its
                   ^      session settings and errors, the command line all of it)
                   |
               dashboard  (the fleet's web page: on the SDK alone; the command line serves it)

``gateway.sim`` (the simulators) stands beside the gateway: it uses the codecs, the bus clock
and the protocol table, and nothing of the gateway's service uses it but the command line.
``gateway.trajectory`` (trajectories played by the gateway: their pure sampling and bounds,
their checks, verdicts and lanes) stands on the scheduler; the API's bridge serves it.
``errors`` (busgate's one exception tree) is below every room: each may import it."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
GATEWAY_ROOMS = ("api", "bus", "cli", "drivers", "recording", "scheduler", "service", "sim",
                 "trajectory")

#: Each room and the rooms it may import ("gateway" is the package itself: its version).
#: The folders that install as busgate's rooms.
FOLDERS = ("client", "codecs", "dashboard", "errors", "schemas", "gateway")
#: The room every other may import: the exception tree.
BELOW_ALL = "errors"

ALLOWED: dict[str, set[str]] = {
    "errors": set(),  # busgate's one exception tree: every room may import it (BELOW_ALL)
    "codecs": set(),
    "schemas": {"codecs"},
    "client": {"codecs", "schemas"},
    "dashboard": {"codecs", "schemas", "client"},
    "gateway": set(),
    "gateway.bus": {"codecs"},
    "gateway.drivers": {"codecs", "schemas", "gateway.bus"},
    "gateway.scheduler": {"codecs", "schemas", "gateway.bus", "gateway.drivers"},
    "gateway.api": {"codecs", "schemas", "client", "gateway", "gateway.bus", "gateway.drivers",
                    "gateway.scheduler", "gateway.trajectory"},
    "gateway.service": {"codecs", "schemas", "client", "gateway", "gateway.bus",
                        "gateway.drivers", "gateway.scheduler", "gateway.api",
                        "gateway.recording", "gateway.trajectory"},
    "gateway.sim": {"codecs", "schemas", "gateway.bus", "gateway.drivers"},
    "gateway.trajectory": {"codecs", "schemas", "gateway.bus", "gateway.drivers",
                           "gateway.scheduler"},
    "gateway.recording": {"codecs", "schemas", "gateway.bus"},
    "gateway.cli": {"codecs", "schemas", "client", "dashboard", "gateway", "gateway.bus",
                    "gateway.drivers", "gateway.recording", "gateway.scheduler", "gateway.api",
                    "gateway.service", "gateway.sim", "gateway.trajectory"},
}


def room_of_file(path: Path) -> str:
    parts = path.relative_to(ROOT).parts
    if parts[0] == "gateway" and len(parts) > 2:
        return f"gateway.{parts[1]}"
    return parts[0]


def room_of_module(name: str) -> str:
    parts = name.split(".")[1:]  # without "busgate"
    if parts[0] == "gateway" and len(parts) > 1 and parts[1] in GATEWAY_ROOMS:
        return f"gateway.{parts[1]}"
    return parts[0]


def imported(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("busgate"):
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names if a.name.startswith("busgate"))
    return {name for name in names if name != "busgate"}


def test_every_import_follows_the_arrows() -> None:
    wrong = []
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            room = room_of_file(path)
            for name in imported(path):
                target = room_of_module(name)
                if target not in {room, BELOW_ALL} and target not in ALLOWED[room]:
                    wrong.append(f"{path.relative_to(ROOT)} ({room}) imports {name} ({target})")
    assert wrong == []


#: A string that names a module of the package (``module`` or ``module:attribute``), the way an
#: import by name is written.
MODULE_NAME = re.compile(r"^busgate(\.\w+)+(:\w+)?$")


def test_no_string_names_a_module_against_the_arrows() -> None:
    """An import by name (``importlib``, a registry of ``module:Class`` paths) is an arrow the
    test above cannot see: no string in a room may name a module of a room it may not
    import. (The registry once named the drivers and simulators this way, from the schemas.)
    A program run as a child (``python -m MODULE``) is no import."""
    wrong = []
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            room = room_of_file(path)
            tree = ast.parse(path.read_text())
            for name in _module_names(tree) - _programs_run(tree):
                target = room_of_module(name.partition(":")[0])
                if target not in {room, BELOW_ALL} and target not in ALLOWED[room]:
                    wrong.append(f"{path.relative_to(ROOT)} ({room}) names {name}")
    assert wrong == []


def _module_names(tree: ast.AST) -> set[str]:
    """Strings that name a module, and f-strings whose fixed start does
    (``f"busgate.gateway.drivers.{name}"``: the part before the first field)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr) and node.values:
            first = node.values[0]
            start = str(first.value).rstrip(".:") if isinstance(first, ast.Constant) else ""
            if MODULE_NAME.match(start):
                found.add(start)
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
              and MODULE_NAME.match(node.value)):
            found.add(node.value)
    return found


def _programs_run(tree: ast.AST) -> set[str]:
    """The modules an argument list runs as a program: what follows ``"-m"``."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.List):
            for flag, name in zip(node.elts, node.elts[1:], strict=False):
                if isinstance(flag, ast.Constant) and flag.value == "-m" and (
                        isinstance(name, ast.Constant) and isinstance(name.value, str)):
                    found.add(name.value)
    return found


def test_every_room_is_described() -> None:
    rooms = set(FOLDERS) | {
        f"gateway.{p.name}" for p in (ROOT / "gateway").iterdir() if (p / "__init__.py").exists()}
    assert rooms == set(ALLOWED)
    architecture = (ROOT / "docs" / "architecture.md").read_text()
    for room in rooms:
        assert f"`{room}`" in architecture, f"docs/architecture.md says nothing of {room}"


#: What the repository must not lean on: files that are not in it, and issue numbers.
OUTSIDE = re.compile("|".join([r"DESIGN\.md", r"PROTOCOL_" + r"NOTES", r"\.\./shared",
                               r"\b[Ii]ssue " + r"\d", r"\bthe " + r"issue\b"]))


def test_nothing_refers_to_a_file_outside_the_repository_or_to_an_issue() -> None:
    found = []
    for path in sorted(ROOT.rglob("*")):
        relative = path.relative_to(ROOT)
        if relative.parts[0] in {".git", ".venv"} or not path.is_file():
            continue
        if relative.parts[:2] in {("tools", "typecheck"), ("tools", "mutation")}:
            continue
        if path.suffix not in {".py", ".md", ".toml", ".json5", ".service", ".rules", ""}:
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if OUTSIDE.search(line):
                found.append(f"{relative}:{number}: {line.strip()}")
    assert found == []


HEAVY = ("zenoh", "serial", "can", "prometheus_client")


@pytest.mark.parametrize("argv", [None, ["--help"], ["encode", "inspire_la", "--id", "3",
                                                       '{"op":"move","position":1000}']])
def test_the_command_line_loads_only_what_its_command_needs(argv) -> None:
    """``busgate --help`` and ``busgate encode`` load none of the heavy libraries: each command's
    module is imported only when that command runs."""
    run = "" if argv is None else (
        f"import contextlib\nfrom busgate.gateway.cli import main\n"
        f"with contextlib.suppress(SystemExit):\n    main({argv!r})\n")
    probe = (f"import busgate.gateway.cli\n{run}import sys\n"
             f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                            check=True)
    assert result.stdout.splitlines()[-1] == "[]"
