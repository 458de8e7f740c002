"""Runs the doctests of every busgate module: codec docstrings show real frames from the
manuals, and those examples must stay true."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import busgate.codecs
import busgate.gateway
import busgate.schemas


def _modules() -> list[str]:
    names = []
    for package in (busgate.codecs, busgate.schemas, busgate.gateway):
        names.append(package.__name__)
        for info in pkgutil.walk_packages(package.__path__, prefix=package.__name__ + "."):
            names.append(info.name)
    return sorted(names)


@pytest.mark.parametrize("name", _modules())
def test_doctests(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
