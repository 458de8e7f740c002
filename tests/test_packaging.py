"""The namespaced layout's guards (docs/architecture.md): a subpackage missing from pyproject's
``packages`` silently vanishes from the wheel, and the top-level folders must never be
importable under their bare names."""

from __future__ import annotations

import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {"client": "busgate.client", "codecs": "busgate.codecs",
           "dashboard": "busgate.dashboard", "errors": "busgate.errors",
           "gateway": "busgate.gateway", "schemas": "busgate.schemas"}


def _packages_on_disk() -> set[str]:
    found = set()
    for folder, package in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            relative = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((package, *relative)))
    return found


def test_pyproject_lists_every_package() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert set(config["tool"]["setuptools"]["packages"]) == _packages_on_disk()


def test_every_package_imports_under_busgate() -> None:
    for package in sorted(_packages_on_disk()):
        importlib.import_module(package)


def test_stdlib_codecs_is_not_shadowed() -> None:
    import codecs

    assert hasattr(codecs, "lookup"), "the standard library's codecs must stay importable"


def test_console_script_runs() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "busgate.gateway.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "encode" in result.stdout and "decode" in result.stdout


def test_the_view_for_static_tools_maps_busgate_onto_the_folders() -> None:
    """``tools/typecheck/busgate/<folder>`` leads to each folder, by a relative link that survives
    a clone anywhere (docs/architecture.md: static tools and editors)."""
    for folder in FOLDERS:
        link = ROOT / "tools" / "typecheck" / "busgate" / folder
        assert link.is_symlink() and not Path(link.readlink()).is_absolute(), link
        assert link.resolve() == (ROOT / folder).resolve()
