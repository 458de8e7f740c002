"""The rooms of the house and the arrows between them (docs/architecture.md): each package
imports only the ones below it. A new import against the arrows fails here, naming the file.

    codecs  <-  schemas  <-  gateway.drivers  <-  gateway.scheduler  <-  gateway.api
       ^           ^            |                                         ^
       +---- gateway.bus <------+                          gateway.service <- gateway.cli
                   |
                 client  (the SDK: codecs' errors and the schemas; the daemon uses its
                   ^      ConnectError, the command line all of it)
                   |
               dashboard  (the fleet's web page: on the SDK alone; the command line serves it)

``gateway.sim`` (the simulators) stands beside the gateway: it uses the codecs, the bus clock
and the protocol table, and nothing of the gateway's service uses it but the command line.
``gateway.trajectory`` (trajectories played by the gateway: their pure sampling and bounds,
their checks, verdicts and lanes) stands on the scheduler; the API's bridge serves it.
``errors`` (busgate's one exception tree) is below every room: each may import it.
The zenoh session settings (``schemas.zenoh_session``) are the data layer's, below both the
daemon and the SDK."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
GATEWAY_ROOMS = ("api", "base", "bus", "cli", "drivers", "recording", "ros2", "scheduler",
                 "service", "sim", "trajectory")

#: The folders that install as busgate's rooms.
FOLDERS = ("client", "codecs", "dashboard", "errors", "schemas", "gateway")
#: The room every other may import: the exception tree.
BELOW_ALL = "errors"

#: docs/architecture.md's table of the rooms, each with what it may import: the one list of
#: the arrows, which this test holds the code to (a copy here once differed from the doc's).
ARCHITECTURE = ROOT / "docs" / "architecture.md"
_ROW = re.compile(r"^\| `(?P<room>[\w.]+)` \| (?P<imports>[^|]*) \|", re.M)


_NAMES = re.compile(r"nothing of busgate|`[\w.]+`(, `[\w.]+`)*")


def rooms_in_the_docs() -> dict[str, set[str]]:
    """Each row's room and the rooms its second column names; that column is names alone
    (or "nothing of busgate"): prose there ("everything but `x`") would allow ``x``."""
    text = ARCHITECTURE.read_text()
    table = text[text.index("| room | may import |") :]
    table = table[: table.index("\n\n")]
    rows = list(_ROW.finditer(table))
    prose = [row["room"] for row in rows if not _NAMES.fullmatch(row["imports"].strip())]
    assert prose == [], f"docs/architecture.md: rows whose imports are not names alone: {prose}"
    return {row["room"]: set(re.findall(r"`([\w.]+)`", row["imports"])) for row in rows}


ALLOWED: dict[str, set[str]] = rooms_in_the_docs()


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


#: The modules that import ``zenoh`` (docs/architecture.md names them): the session settings,
#: the SDK's core and keys, the daemon's bridge (and its start, for the one error it turns into
#: a refusal), and the command line's router and recorder. Every other client goes through the
#: SDK.
ZENOH_IMPORTERS = {
    "schemas/zenoh_session.py",
    "client/core.py",
    "client/keys.py",
    "gateway/api/bridge.py",
    "gateway/api/intake.py",
    "gateway/service/daemon.py",
    "gateway/cli/router.py",
    "gateway/ros2/node.py",
}


def test_only_the_listed_modules_import_zenoh() -> None:
    found = set()
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                if any(name.split(".")[0] == "zenoh" for name in names):
                    found.add(path.relative_to(ROOT).as_posix())
    assert found == ZENOH_IMPORTERS


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


# -- docs/architecture.md names only modules that exist -------------------------------------------

ARCHITECTURE = ROOT / "docs" / "architecture.md"
CODE_SPAN = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")
IDENTIFIER = re.compile(r"[a-z_][a-z0-9_]*")
DOTTED = re.compile(r"[a-z_]\w*(?:\.\w+)+")


def _module(parts: list[str]) -> tuple[Path | None, list[str]]:
    """The file of the longest module that ``parts`` (``["gateway", "api", "bridge"]``)
    start with, and the parts left over (names defined in it); ``None`` when not even the
    first part is a folder of the package."""
    if parts[0] not in FOLDERS:
        return None, parts
    path, at = ROOT / parts[0], 1
    while at < len(parts) and path.is_dir():
        if (path / parts[at] / "__init__.py").exists():
            path = path / parts[at]
        elif (path / f"{parts[at]}.py").exists():
            path = path / f"{parts[at]}.py"
        else:
            break
        at += 1
    return (path / "__init__.py" if path.is_dir() else path), parts[at:]


def _defines(path: Path, name: str) -> bool:
    """Whether the module at ``path`` defines or imports ``name`` at its top level."""
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names = [node.name]
        elif isinstance(node, ast.Assign):
            names = [t.id for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names = [node.target.id]
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names = [(a.asname or a.name).split(".")[0] for a in node.names]
        else:
            continue
        if name in names:
            return True
    return False


def _dotted_problem(name: str, *, module_only: bool = False) -> str | None:
    """What is wrong with the dotted name ``name`` (``schemas.encoding.message_json``,
    ``busgate.client.aio``): nothing (``None``), or why it names nothing."""
    path, rest = _module(name.removeprefix("busgate.").split("."))
    if path is None or not path.exists():
        return f"`{name}`: no such module"
    if rest and module_only:
        return f"`{name}`: no such module ({path.relative_to(ROOT)} has no {rest[0]})"
    if rest and not _defines(path, rest[0]):
        return f"`{name}`: {path.relative_to(ROOT)} has no {rest[0]}"
    return None


def rooms_table() -> list[tuple[str, str, str]]:
    """(room, folder, what it is) of each row of the rooms table."""
    text = ARCHITECTURE.read_text()
    table = text.split("## The rooms", 1)[1].split("\n#", 1)[0]
    rows = []
    for line in table.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0].startswith("`"):
            rows.append((cells[0].strip("`"), cells[1].strip("`"), cells[2]))
    return rows


def architecture_names() -> dict[str, str | None]:
    """Every module docs/architecture.md names, and what is wrong with each (``None``).

    Exact by these rules of the page: in the rooms table's third column a backticked
    lowercase name is a module (or package) of the room's folder (``commands`` in
    ``gateway/api/``; a function carries its parentheses, ``now()``, and ``busgate`` is the
    program); anywhere on the page a backticked dotted name that starts with a folder of the
    package (``schemas.replies``, ``busgate.client.aio``) is a module, perhaps followed by a
    name defined in it (``schemas.encoding.message_json``); a backticked path ending in
    ``.py`` is a file from the repository's root (``gateway/scheduler/execution.py``) or, bare,
    the one file of that name in the package (``inspire_la_table.py``). Paths of a pattern
    (``gateway/drivers/<protocol>.py``) name no file."""
    found: dict[str, str | None] = {}
    for _, folder, what in rooms_table():
        package = folder.removesuffix("/__init__.py").strip("/").replace("/", ".")
        for span in CODE_SPAN.findall(what):
            if IDENTIFIER.fullmatch(span) and span != "busgate":
                found[f"{package}.{span}"] = _dotted_problem(f"{package}.{span}",
                                                             module_only=True)
    code = [p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py")]
    for span in CODE_SPAN.findall(ARCHITECTURE.read_text()):
        if DOTTED.fullmatch(span) and span.removeprefix("busgate.").split(".")[0] in FOLDERS:
            found[span] = _dotted_problem(span)
        elif span.endswith(".py") and "<" not in span:
            if "/" in span:
                found[span] = None if (ROOT / span).is_file() else f"`{span}`: no such file"
            else:
                files = [p for p in code if p.name == span]
                found[span] = None if len(files) == 1 else f"`{span}`: {len(files)} such files"
    return found


def test_every_module_the_architecture_names_exists() -> None:
    names = architecture_names()
    assert {"gateway.api.commands", "gateway/scheduler/execution.py"} <= set(names)
    assert len(names) > 50, "the rooms table was read"
    assert [problem for problem in names.values() if problem] == []


def test_the_architecture_names_a_module_the_way_its_rules_say() -> None:
    assert "has no protocols" in str(_dotted_problem("gateway.drivers.protocols",
                                                     module_only=True))
    assert _dotted_problem("schemas.encoding.message_json") is None
    assert _dotted_problem("schemas.encoding.no_such_name") is not None
    assert _dotted_problem("gateway.scheduler.execution", module_only=True) is None
