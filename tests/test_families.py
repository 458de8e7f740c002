"""The family registry (schemas/families.py) and the gateway's tables beside it (the drivers'
``DRIVERS``, the simulators' ``MODELS``, the demo's buses): every table derives from the
registry or is held to it, a family missing a part is refused naming the part, and a new
family is its modules, one entry and a row in each of the gateway's two tables.

The throwaway family ("la_clone") is built from the Inspire LA's modules: a codec, schema,
driver and simulator module of its own that reuse the LA's code, one ``Family`` and its two
rows. It runs in a child process, since registering must come before the schemas build their
types.
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from busgate.codecs import inspire_la
from busgate.errors import FamilyError
from busgate.gateway.cli.demo import DEMO_BUSES
from busgate.gateway.drivers import families
from busgate.gateway.drivers.base import Effect
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.families import DRIVERS, check_family, driver_class
from busgate.gateway.sim import models
from busgate.gateway.sim.models import MODELS, model_class
from busgate.schemas import api
from busgate.schemas.config import parse_config
from busgate.schemas.families import FAMILIES, PROTOCOLS, Family, WireProtocol, register

ROOT = Path(__file__).resolve().parent.parent


def test_every_registered_family_has_every_part() -> None:
    for family in FAMILIES.values():
        check_family(family)
        for protocol in family.protocols:
            assert driver_class(protocol).protocol_entry() is protocol
            model_class(protocol.name)


def test_the_tables_are_the_registry() -> None:
    kinds = set(FAMILIES)
    assert set(api.DEVICE_COMMAND_ADAPTERS) == set(api.TELEMETRY_MODELS) == kinds
    assert set(api.FOLLOW_MODELS) == kinds
    assert {bus.protocol for bus in DEMO_BUSES} == set(PROTOCOLS)
    assert set(api.ProtocolName.__args__) == set(PROTOCOLS)
    assert set(DRIVERS) == set(MODELS) == set(PROTOCOLS)


def _bus(kind: str, transport: str, ids: list[int]) -> dict:
    link = ({"port": "/dev/null", "baudrate": 115200} if transport == "serial"
            else {"interface": "virtual", "channel": "x"})
    return {"name": "b", "transport": transport, **link,
            "devices": [{"name": f"d{i}", "kind": kind, "id": i} for i in ids]}


@pytest.mark.parametrize("transport", ["serial", "can"])
@pytest.mark.parametrize("kind", sorted(FAMILIES))
def test_a_config_takes_a_kind_where_the_registry_puts_it(kind: str, transport: str) -> None:
    protocol = FAMILIES[kind].on(transport)
    document = {"gateway": {"name": "g"}, "buses": [_bus(kind, transport, [1])]}
    if protocol is None:
        with pytest.raises(ValueError, match=f"{kind} cannot be on a {transport} bus"):
            parse_config(document)
        return
    assert parse_config(document).buses[0].protocol == protocol.name
    ids = protocol.device_ids
    document["buses"] = [_bus(kind, transport, [ids[-1] + 1])]
    with pytest.raises(ValueError, match=f"outside {ids[0]}–{ids[-1]}"):
        parse_config(document)
    if not protocol.addressed:
        document["buses"] = [_bus(kind, transport, [1, 2])]
        with pytest.raises(ValueError, match="carry no device id"):
            parse_config(document)


def test_every_uart_protocol_keeps_1_ms_of_idle_line_by_default() -> None:
    """The gateway's rule for every UART exchange, the LA manual's figure; the DS and RS232
    manuals state no gap, and their buses kept 0.5 ms (an outside wire audit measured half
    the DS gaps under 1 ms). CAN arbitrates: no gap."""
    defaults = {name: p.timing.default_gap_s for name, p in PROTOCOLS.items()}
    assert {n: g for n, g in defaults.items() if not PROTOCOLS[n].can and g < 0.001} == {}
    assert all(gap == 0 for name, gap in defaults.items() if PROTOCOLS[name].can)


def test_a_kind_or_protocol_is_registered_once() -> None:
    la = FAMILIES["inspire_la"]
    with pytest.raises(ValueError, match="inspire_la already registered"):
        register(la)
    assert FAMILIES["inspire_la"] is la


# --- a family missing a part --------------------------------------------------------------------

#: Modules of a broken family, each lacking one part.
BROKEN = {
    "no_timing_codec": "from busgate.codecs.inspire_la import encode, expected_reply, "
                       "CommandDecoder, ReplyDecoder, readings, DEVICE_IDS, ADDRESSED\n",
    "no_follow_schema": "from busgate.schemas.inspire_la import Command, COMMAND_ADAPTER, "
                        "TELEMETRY_MODEL\n",
    "no_probe_driver": textwrap.dedent("""\
        import abc
        from busgate.gateway.drivers.inspire_la import InspireLaDriver
        class NoProbe(InspireLaDriver):  # a driver whose author left the scan probe out
            @classmethod
            @abc.abstractmethod
            def probe(cls, device_id): ...
        """),
    "no_handle_sim": "class Device:\n    def accepts(self, command): return True\n",
}


@pytest.fixture
def broken_modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name, text in BROKEN.items():
        (tmp_path / f"{name}.py").write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))


def _family(codec: str = "busgate.codecs.inspire_la",
            schema: str = "busgate.schemas.inspire_la") -> Family:
    protocol = WireProtocol("inspire_la", "inspire_la", "serial", importlib.import_module(codec))
    return Family("inspire_la", (protocol,), schema_module=schema)


@pytest.mark.usefixtures("broken_modules")
@pytest.mark.parametrize(("parts", "named"), [
    ({"codec": "no_timing_codec"}, "codec no_timing_codec has no TIMING"),
    ({"schema": "no_follow_schema"}, "schema module no_follow_schema has no FollowTarget"),
    ({"schema": "busgate.schemas.no_such"}, "its schema module cannot be imported"),
    ({"schema": "busgate.schemas.ds_servo"}, "telemetry model's kind is not 'inspire_la'"),
])  # fmt: skip
def test_a_family_missing_a_part_is_refused_naming_it(parts: dict, named: str) -> None:
    with pytest.raises(FamilyError, match=named):
        check_family(_family(**parts))


def _no_probe() -> type:
    return importlib.import_module("no_probe_driver").NoProbe


@pytest.mark.usefixtures("broken_modules")
@pytest.mark.parametrize(("row", "named"), [
    (None, "no driver is registered for it"),
    (_no_probe, "driver NoProbe does not define probe"),
    (lambda: Effect, "driver Effect is not a Driver class"),
    (lambda: DsServoDriver, "driver DsServoDriver names another protocol"),
])  # fmt: skip
def test_a_protocol_whose_driver_row_is_missing_or_wrong_is_refused_naming_it(
        monkeypatch: pytest.MonkeyPatch, row, named: str) -> None:
    if row is None:
        monkeypatch.delitem(families.DRIVERS, "inspire_la")
    else:
        monkeypatch.setitem(families.DRIVERS, "inspire_la", row())
    with pytest.raises(FamilyError, match=named):
        check_family(_family())


@pytest.mark.usefixtures("broken_modules")
def test_a_simulator_missing_a_part_is_refused_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    broken = importlib.import_module("no_handle_sim").Device
    monkeypatch.setitem(models.MODELS, "inspire_la", broken)
    with pytest.raises(FamilyError, match="simulator Device has no handle"):
        model_class("inspire_la")
    monkeypatch.delitem(models.MODELS, "inspire_la")
    with pytest.raises(FamilyError, match="no simulator model is registered"):
        model_class("inspire_la")
    assert inspire_la.TIMING  # the codec itself was never the problem


# --- a fifth family: four modules, one entry and two rows -----------------------------------------

CLONE_MODULES = {
    "la_clone_codec": "from busgate.codecs.inspire_la import *  # noqa: F403\n",
    "la_clone_schema": textwrap.dedent("""\
        from typing import Literal
        from busgate.schemas.inspire_la import Command, COMMAND_ADAPTER, FollowTarget
        from busgate.schemas.inspire_la import InspireLaTelemetry
        from busgate.schemas.joints import JointDeclaration
        class CloneTelemetry(InspireLaTelemetry):
            kind: Literal["la_clone"]
        TELEMETRY_MODEL = CloneTelemetry
        JOINT = JointDeclaration(raw_range=(0, 2000), position="position", target="target",
                                 move=("move", "position"), follow_position="position")
        """),
    "la_clone_driver": textwrap.dedent("""\
        from busgate.gateway.drivers.inspire_la import InspireLaDriver
        class CloneDriver(InspireLaDriver):
            protocol = "la_clone"
        """),
    "la_clone_sim": textwrap.dedent("""\
        from busgate.gateway.sim.inspire_la import InspireLaDevice
        class CloneDevice(InspireLaDevice):
            pass
        """),
}

#: Registers the clone, then uses it where a user would: a config file, the JSON Schemas, a bus
#: with its driver against its simulator (the real serial owner on a pty), the telemetry.
CLONE_RUN = textwrap.dedent("""\
    import json, sys, time
    import la_clone_codec
    from busgate.schemas.families import Family, WireProtocol, register
    register(Family("la_clone", (WireProtocol("la_clone", "la_clone", "serial", la_clone_codec),),
                    schema_module="la_clone_schema"))

    from la_clone_driver import CloneDriver
    from la_clone_sim import CloneDevice
    from busgate.gateway.drivers.families import DRIVERS, check_family
    from busgate.gateway.sim.models import MODELS
    DRIVERS["la_clone"] = CloneDriver
    MODELS["la_clone"] = CloneDevice
    from busgate.gateway.service.assembly import build_bus
    from busgate.gateway.sim.models import make_devices
    from busgate.gateway.sim.serial_server import SerialSimulator
    from busgate.schemas import api
    from busgate.schemas.config import parse_config
    from busgate.schemas.families import FAMILIES, PROTOCOLS

    check_family(FAMILIES["la_clone"])
    codec = PROTOCOLS["la_clone"].codec
    out = {"schema": list(api.DEVICE_COMMAND_ADAPTERS)}
    with SerialSimulator(codec, make_devices("la_clone", [1]), baudrate=921600) as sim:
        config = parse_config({"gateway": {"name": "g"}, "buses": [{
            "name": "clones", "transport": "serial", "port": sim.port, "baudrate": 921600,
            "devices": [{"name": "c1", "kind": "la_clone", "id": 1, "joint": {
                "name": "slide", "unit": "m", "scale": 1e-5, "max": 0.015}}]}]})
        states = []
        runner = build_bus(config.buses[0], on_state=lambda d, s: states.append(s)).start()
        try:
            deadline = time.monotonic() + 30
            while not runner.drivers["c1"].online and time.monotonic() < deadline:
                time.sleep(0.01)
            driver = runner.drivers["c1"]
            reply = runner.submit("c1", driver.parse('{"op":"move","position":1500}')).result(10)
            out["reply"] = api.TELEMETRY_ADAPTER.validate_python(reply["state"]).target
            out["joint"] = reply["state"]["joint"]["name"]
            try:
                runner.submit("c1", driver.parse('{"op":"move","position":1600}')).result(10)
            except Exception as exc:
                out["beyond"] = str(exc)
            while not states and time.monotonic() < deadline:
                time.sleep(0.01)
            out["state"] = api.TELEMETRY_ADAPTER.validate_python(states[-1]).kind
        finally:
            runner.stop()
    print(json.dumps(out))
""")


def test_a_throwaway_family_built_from_an_existing_one_runs(tmp_path: Path) -> None:
    for name, text in CLONE_MODULES.items():
        (tmp_path / f"{name}.py").write_text(text)
    result = subprocess.run([sys.executable, "-c", CLONE_RUN], capture_output=True, text=True,
                            timeout=120, cwd=tmp_path, env={"PYTHONPATH": str(tmp_path)})
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    assert out == {"schema": ["inspire_la", "ds_servo", "zlac706", "la_clone"], "reply": 1500,
                   "joint": "slide",
                   "beyond": "joint slide: position 0.016 m is beyond its max 0.015 m",
                   "state": "la_clone"}
