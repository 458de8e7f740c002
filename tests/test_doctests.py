"""Runs the doctests of busgate's modules: codec docstrings show real frames from the manuals,
and those examples must stay true.

The modules with doctests are listed here, and the list must be the truth both ways: a listed
module whose examples were lost fails, and so does a module whose new examples were not
listed (so they are run and counted knowingly)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import busgate.client
import busgate.codecs
import busgate.gateway
import busgate.schemas

DOCTEST_MODULES = [
    "busgate.client",
    "busgate.client.core",
    "busgate.client.keys",
    "busgate.client.messages",
    "busgate.codecs.can_frame",
    "busgate.codecs.ds_servo.decoder",
    "busgate.codecs.ds_servo.encoder",
    "busgate.codecs.ds_servo.registers",
    "busgate.codecs.framing",
    "busgate.codecs.inspire_la",
    "busgate.codecs.inspire_la.decoder",
    "busgate.codecs.inspire_la.encoder",
    "busgate.codecs.inspire_la.exchange",
    "busgate.codecs.inspire_la.registers",
    "busgate.codecs.registers",
    "busgate.codecs.ros2.messages",
    "busgate.codecs.ros2.rmw_zenoh",
    "busgate.codecs.ros2.type_hash",
    "busgate.codecs.timing",
    "busgate.codecs.zlac706_can.decoder",
    "busgate.codecs.zlac706_can.encoder",
    "busgate.codecs.zlac706_can.registers",
    "busgate.codecs.zlac706_common",
    "busgate.codecs.zlac706_rs232.decoder",
    "busgate.codecs.zlac706_rs232.encoder",
    "busgate.codecs.zlac706_rs232.monitor",
    "busgate.codecs.zlac706_rs232.registers",
    "busgate.gateway.bus.port_access",
    "busgate.gateway.bus.stats",
    "busgate.gateway.cli.client",
    "busgate.gateway.cli.jsonify",
    "busgate.gateway.drivers.ds_servo",
    "busgate.gateway.drivers.inspire_la_frames",
    "busgate.gateway.drivers.zlac706_can",
    "busgate.gateway.drivers.zlac706_rs232",
    "busgate.gateway.recording.mcap_log",
    "busgate.gateway.ros2.bases",
    "busgate.gateway.scheduler.trajectory_ticks",
    "busgate.gateway.trajectory.bounds",
    "busgate.gateway.trajectory.interpolation",
    "busgate.schemas.endpoints",
    "busgate.schemas.keys",
    "busgate.schemas.payload",
    "busgate.schemas.telemetry",
    "busgate.schemas.validation",
    "busgate.schemas.zenoh_session",
]


def _modules() -> list[str]:
    names = []
    for package in (busgate.client, busgate.codecs, busgate.schemas, busgate.gateway):
        names.append(package.__name__)
        for info in pkgutil.walk_packages(package.__path__, prefix=package.__name__ + "."):
            if not info.name.endswith(".__main__"):  # importing it runs the command
                names.append(info.name)
    return sorted(names)


def _examples(name: str) -> int:
    module = importlib.import_module(name)
    return sum(len(test.examples) for test in doctest.DocTestFinder().find(module))


@pytest.mark.parametrize("name", DOCTEST_MODULES)
def test_doctests(name: str) -> None:
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name} is listed as having doctests and has none"
    assert result.failed == 0


def test_every_module_with_doctests_is_listed() -> None:
    assert [name for name in _modules() if _examples(name)] == DOCTEST_MODULES
