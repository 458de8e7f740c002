"""The rules CI holds the suite to, checked on a throwaway suite run by pytest itself: under
``CI=true`` a test skipped for want of a tool fails; elsewhere it is a skip."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = (Path(__file__).parent / "conftest.py").read_text()
SKIPPING = """
import pytest

def test_needs_a_tool():
    pytest.skip("frobnicate is not installed here (apt-get install frobnicate)")

def test_skips_for_another_reason():
    pytest.skip("the kernel has no such feature")
"""


@pytest.mark.parametrize(("ci", "failed", "skipped"), [("true", 1, 1), ("", 0, 2)])
def test_a_skip_for_a_missing_tool_fails_under_ci(pytester, monkeypatch, ci, failed, skipped):
    monkeypatch.setenv("CI", ci)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(SKIPPING)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(failed=failed, skipped=skipped)
