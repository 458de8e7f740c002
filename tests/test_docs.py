"""The manual, run as it is read: every shell command and Python block of README.md and
docs/*.md, against one ``busgate demo`` for the whole module.

Rules of this file:

1. Every fenced block tagged ``console``, ``sh`` or ``bash`` is run, or says why not in an HTML
   comment on the line before it (``<!-- not run: starts a server -->``), which readers do not
   see. A ``python`` block is always run, as a script. A ``toml`` block parses, and a whole
   config (``[gateway]`` and ``[[buses]]``) passes ``busgate check-config``; a ``json`` block
   parses, and on the trajectories page it is a trajectory command the schema takes.
2. Commands run as a user types them in the activated venv (``busgate``, ``python``), from a
   directory that holds the repository's entries as links (so that ``docs/…`` and
   ``deploy/…`` resolve and what a command writes lands in a fresh place). The documented
   endpoint ``tcp/127.0.0.1:7447`` becomes the demo's; a client command that names none
   (``busgate send``, ``watch``, ``record``, ``replay``) is given the demo's ``--connect``.
3. In a ``console`` block each ``$`` line is one command: it must exit 0, or the status its
   comment names (``# refused: exit status 1``), and print the lines shown under it, in order
   (stdout, then stderr), with the numbers free (they are a run's own), ``…`` standing for
   anything and the columns' spacing free. A ``sh`` block runs as one script and must exit 0.
4. Every ``busgate`` command the pages show, in a block run or not or inline in the text, uses
   only options its parser knows: a renamed flag fails here even where the command cannot run.
5. Every relative link leads to a file, and its ``#anchor`` to a heading of that file; every
   page of docs/ is in the README's table; the SDK's page names every public name of
   ``busgate.client``.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

import busgate.client as bc
from busgate.gateway.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
DOCUMENTED_ENDPOINT = "tcp/127.0.0.1:7447"
RUN_TIMEOUT_S = 30.0  # a hang guard, not a speed requirement
SHELL = {"console", "sh", "bash"}
FENCE = re.compile(r"^```(\w*)\s*$")
NOT_RUN = re.compile(r"^<!--\s*not run:\s*(\S.*?)\s*-->$")
EXIT_STATUS = re.compile(r"#.*\bexit status (\d+)")
#: The client commands that reach a gateway, and so are pointed at the demo.
CLIENT_COMMANDS = ("send", "watch", "record", "replay")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # of the opening fence, from 1
    lang: str
    text: str
    not_run: str | None  # why, when the page says it is not run

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks_of(page: Path) -> list[Block]:
    lines = page.read_text().splitlines()
    found, index = [], 0
    while index < len(lines):
        opening = FENCE.match(lines[index])
        if not opening:
            index += 1
            continue
        end = next(i for i in range(index + 1, len(lines)) if lines[i].startswith("```"))
        before = next((lines[i].strip() for i in range(index - 1, -1, -1) if lines[i].strip()),
                      "")
        marked = NOT_RUN.match(before)
        found.append(Block(page, index + 1, opening.group(1), "\n".join(lines[index + 1:end]),
                           marked.group(1) if marked else None))
        index = end + 1
    return found


BLOCKS = [block for page in PAGES for block in blocks_of(page)]
RUN = [b for b in BLOCKS if b.lang in SHELL | {"python"} and b.not_run is None]


def by_name(blocks: list[Block]) -> dict:
    return {"argvalues": blocks, "ids": [b.name for b in blocks]}


# -- the demo, and where commands run ---------------------------------------------------------


@pytest.fixture(scope="module")
def demo_endpoint(module_demo) -> str:
    """Where the module's demo (``conftest.module_demo``) serves."""
    return module_demo.endpoint


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The repository's entries as links, and ``.venv`` the venv running these tests."""
    where = tmp_path_factory.mktemp("docs")
    for entry in ROOT.iterdir():
        if entry.name not in {".git", ".venv"}:
            (where / entry.name).symlink_to(entry)
    (where / ".venv").symlink_to(Path(sys.prefix))
    return where


def environment() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = sys.prefix
    env.pop("BUSGATE_PASSWORD", None)
    return env


def for_the_demo(command: str, endpoint: str) -> str:
    command = command.replace(DOCUMENTED_ENDPOINT, endpoint)
    if "--connect" not in command:
        command = re.sub(rf"\bbusgate ({'|'.join(CLIENT_COMMANDS)})\b",
                         rf"busgate \1 --connect {endpoint}", command)
    return command


def run_shell(script: str, workdir: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", script], cwd=workdir, env=environment(),
                          capture_output=True, text=True, timeout=RUN_TIMEOUT_S)


# -- rule 3: what a console command prints ----------------------------------------------------

NUMBER = re.compile(r"(?<![A-Za-z_])\\?-?\d+(?:\\?\.\d+)?")


def pattern_of(shown: str) -> re.Pattern[str]:
    """A shown line as a pattern: numbers free, ``…`` anything, spacing free."""
    parts = []
    for word in shown.split():
        pieces = [re.escape(piece) for piece in word.split("…")]
        pieces = [NUMBER.sub(r"-?\\d+(?:\\.\\d+)?(?:e-?\\d+)?", piece) for piece in pieces]
        parts.append(".*".join(pieces))
    return re.compile(r"\s*" + r"\s+".join(parts) + r"\s*")


def missing_lines(shown: list[str], printed: list[str]) -> list[str]:
    """The shown lines not found in order among the printed ones (all found: [])."""
    at = 0
    for number, line in enumerate(shown):
        pattern = pattern_of(line)
        while at < len(printed) and not pattern.fullmatch(printed[at]):
            at += 1
        if at == len(printed):
            return shown[number:]
        at += 1
    return []


def console_commands(text: str) -> list[tuple[str, list[str]]]:
    commands: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        if line.startswith("$ "):
            commands.append((line[2:], []))
        elif line.strip():
            assert commands, f"output before any command: {line!r}"
            commands[-1][1].append(line)
    return commands


def test_a_shown_line_matches_with_other_numbers_and_elisions() -> None:
    assert missing_lines(["la1  inspire_la  yes  1500 -> 1500  0.1s"],
                         ["la0 x", "la1     inspire_la  yes     1498 -> 1500    2.3s"]) == []
    assert missing_lines(['{"ok": true, "ts": …, "target": 1500, …}'],
                         ['{"ok": true, "ts": 1796290786.7084966, "target": 1200, "x": 1}']) == []
    assert missing_lines(["uart0  3%"], ["uart1  3%"]) == ["uart0  3%"]
    assert missing_lines(["a", "b"], ["b", "a"]) == ["b"]


# -- rules 1–3: the blocks, run -----------------------------------------------------------------


@pytest.mark.parametrize("block", **by_name(RUN))
def test_the_block_runs_as_documented(block: Block, demo_endpoint: str, workdir: Path) -> None:
    if block.lang == "python":
        script = workdir / f"block-{block.page.stem}-{block.line}.py"
        script.write_text(for_the_demo(block.text, demo_endpoint))
        done = subprocess.run([sys.executable, str(script)], cwd=workdir, env=environment(),
                              capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
        assert done.returncode == 0, done.stderr
    elif block.lang == "console":
        for command, shown in console_commands(block.text):
            done = run_shell(for_the_demo(command, demo_endpoint), workdir)
            status = EXIT_STATUS.search(command)
            expected = int(status.group(1)) if status else 0
            assert done.returncode == expected, f"$ {command}\n{done.stdout}{done.stderr}"
            printed = done.stdout.splitlines() + done.stderr.splitlines()
            assert missing_lines(shown, printed) == [], f"$ {command}\n" + "\n".join(printed)
    else:
        done = run_shell("set -e\n" + for_the_demo(block.text, demo_endpoint), workdir)
        assert done.returncode == 0, f"{block.text}\n{done.stdout}{done.stderr}"


def test_every_block_is_run_or_says_why_not() -> None:
    """Rule 1: a block the test cannot run says why; a reason on a block that is never run
    anyway (or on a Python block, always run) is a mistake."""
    wrong = [b.name for b in BLOCKS if b.not_run is not None and b.lang not in SHELL]
    assert wrong == []
    assert RUN, "the pages have blocks to run"


@pytest.mark.parametrize("block", **by_name([b for b in BLOCKS if b.lang == "toml"]))
def test_a_toml_block_parses_and_a_whole_config_is_valid(block: Block, workdir: Path) -> None:
    config = tomllib.loads(block.text)
    if {"gateway", "buses"} <= set(config):
        path = workdir / f"config-{block.page.stem}-{block.line}.toml"
        path.write_text(block.text)
        done = run_shell(f"busgate check-config {shlex.quote(str(path))}", workdir)
        assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.parametrize("block", **by_name([b for b in BLOCKS if b.lang == "json"]))
def test_a_json_block_parses_and_a_trajectory_command_validates(block: Block) -> None:
    body = json.loads(block.text)
    if block.page.name == "trajectories.md":
        from busgate.schemas.trajectory import TRAJECTORY_COMMAND_ADAPTER

        TRAJECTORY_COMMAND_ADAPTER.validate_python(body)


# -- rule 4: every busgate command's options ----------------------------------------------------

INLINE_CODE = re.compile(r"(?<!`)`([^`]+)`(?!`)")
SEPARATORS = {"&&", "||", "|", ";", "&"}


def command_lines() -> list[tuple[str, str]]:
    """(where, line) of every command line of a shell block and every inline code span."""
    found = []
    for block in BLOCKS:
        if block.lang in SHELL:
            for line in block.text.splitlines():
                if block.lang != "console" or line.startswith("$ "):
                    found.append((block.name, line.removeprefix("$ ")))
    for page in PAGES:
        for span in INLINE_CODE.findall(page.read_text()):
            if span.startswith("busgate "):
                found.append((str(page.relative_to(ROOT)), span.replace("\n", " ")))
    return found


def options_of(command: str | None) -> set[str]:
    parser = build_parser(command)
    if command is None:
        return set(parser._option_string_actions)
    subparsers = next(a for a in parser._actions if a.choices and command in a.choices)
    return set(subparsers.choices[command]._option_string_actions)


def unknown_options(line: str) -> list[str]:
    text = line.replace("[", " ").replace("]", " ").replace("…", " ")
    try:
        words = shlex.split(text, comments=True)
    except ValueError:  # an unbalanced quote in prose: the words as they are
        words = text.split()
    wrong = []
    for at, word in enumerate(words):
        if word != "busgate" and not word.endswith("/busgate"):
            continue
        rest = words[at + 1:]
        if not rest or rest[0] == "busgate" or rest[0].endswith(":"):
            continue  # `sudo -u busgate busgate …`, or a message: `busgate router: …`
        command = None if rest[0].startswith("-") else rest[0]
        if command is not None and command not in COMMANDS:
            wrong.append(f"no command {command!r}")
            continue
        known = options_of(command)
        for arg in rest[0 if command is None else 1:]:
            if arg in SEPARATORS:
                break
            option = arg.split("=", 1)[0]
            if re.fullmatch(r"--[\w-]+|-[A-Za-z]", option) and option not in known:
                wrong.append(f"{command or 'busgate'} has no {option}")
    return wrong


def test_every_busgate_command_shown_uses_options_its_parser_knows() -> None:
    lines = command_lines()
    shell_blocks = {b.name for b in BLOCKS if b.lang in SHELL}
    assert shell_blocks <= {where for where, _ in lines}, "every block, run or not"
    wrong = [f"{where}: {line}: {problem}" for where, line in lines
             for problem in unknown_options(line)]
    assert wrong == []


def test_a_renamed_option_is_caught() -> None:
    assert unknown_options("busgate watch --one") == ["watch has no --one"]
    assert unknown_options("busgate sned la1 '{}'") == ["no command 'sned'"]
    assert unknown_options("busgate record -o x.mcap [--seconds N] && busgate --version") == []


# -- rule 5: links, the table of pages, the SDK's names ----------------------------------------

LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchors(page: Path) -> set[str]:
    found = set()
    in_fence = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            in_fence = not in_fence
        elif not in_fence and (heading := re.match(r"#{1,6}\s+(.*)", line)):
            text = heading.group(1).strip().lower().replace("`", "")
            found.add(re.sub(r"[^\w\- ]", "", text).replace(" ", "-"))
    return found


def test_every_link_leads_to_a_file_and_a_heading() -> None:
    wrong = []
    for page in PAGES:
        for target in LINK.findall(page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue  # https:, mailto:
            path, _, anchor = target.partition("#")
            linked = (page.parent / path).resolve() if path else page
            if not linked.exists():
                wrong.append(f"{page.relative_to(ROOT)}: {target}: no such file")
            elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
                wrong.append(f"{page.relative_to(ROOT)}: {target}: no such heading")
    assert wrong == []


def test_the_readme_lists_every_page_of_the_manual() -> None:
    readme = (ROOT / "README.md").read_text()
    listed = {Path(target.partition("#")[0]).name for target in LINK.findall(readme)
              if target.startswith("docs/")}
    assert {page.name for page in (ROOT / "docs").glob("*.md")} <= listed


def test_the_sdk_page_names_every_public_name() -> None:
    page = (ROOT / "docs" / "sdk.md").read_text()
    unnamed = [name for name in bc.__all__
               if not re.search(rf"`(?:bc\.)?{re.escape(name)}\b", page)]
    assert unnamed == []
