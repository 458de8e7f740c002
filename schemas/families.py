"""The device families busgate drives, each described once: the registry.

Rules of this file:

1. A family is one ``Family`` entry in ``FAMILIES``; every table of kinds, protocols,
   transports, id ranges, timing, telemetry models, command schemas, drivers, simulator models
   and demo devices derives from it. Nothing else lists the families.
2. Wire facts (timing, device ids, whether frames carry an id) belong to the protocol's codec
   and are read from it (``TIMING``, ``DEVICE_IDS``, ``ADDRESSED``); a family's JSON side
   (commands, follow payload, telemetry) belongs to its schema module; what the gateway does
   with a device (frames under the device's rules, scan probe, group moves, follow stream,
   deadman stop) belongs to its driver class. The entry only names them.
3. Parts are named by import path and loaded on first use: the schemas sit below the gateway,
   so this file imports no gateway code, and ``busgate --help`` loads no family at all.
   ``busgate.gateway.families`` loads the gateway's parts and checks that a family has every
   part, naming the one that is missing.

Adding a family: its codec (``busgate.codecs.<protocol>``), schema (``busgate.schemas.<kind>``),
driver and simulator modules, then one ``Family`` here (docs/architecture.md has the recipe).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Literal

from busgate.codecs.timing import ProtocolTiming

Transport = Literal["serial", "can"]


@dataclass(frozen=True, slots=True)
class Demo:
    """What ``busgate demo`` simulates of a protocol: a bus's name and its devices (name, id)."""

    bus: str
    devices: tuple[tuple[str, int], ...]


@dataclass(frozen=True, slots=True)
class WireProtocol:
    """One wire protocol of a family: how its frames travel and what drives and simulates a
    device speaking it (``module:Class`` import paths)."""

    name: str
    kind: str
    transport: Transport
    codec_module: str
    driver: str
    simulator: str
    demo: Demo

    @property
    def codec(self) -> ModuleType:
        return importlib.import_module(self.codec_module)

    @property
    def timing(self) -> ProtocolTiming:
        return self.codec.TIMING

    @property
    def device_ids(self) -> range:
        """The ids a device of this protocol can have (a configuration's ``id``)."""
        return self.codec.DEVICE_IDS

    @property
    def addressed(self) -> bool:
        """Frames carry a device id; when not, a port drives one device."""
        return self.codec.ADDRESSED

    @property
    def can(self) -> bool:
        """Frames are CAN frames rather than a byte stream."""
        return self.transport == "can"

    @property
    def schema(self) -> ModuleType:
        return FAMILIES[self.kind].schema


@dataclass(frozen=True, slots=True)
class Family:
    """A device family: its kind (the ``kind`` of a configured device), its schema module (the
    JSON commands, follow payload and telemetry model), and one ``WireProtocol`` per transport."""

    kind: str
    schema_module: str
    protocols: tuple[WireProtocol, ...]

    @property
    def schema(self) -> ModuleType:
        return importlib.import_module(self.schema_module)

    def on(self, transport: str) -> WireProtocol | None:
        """The family's protocol on ``transport``, if it has one."""
        return next((p for p in self.protocols if p.transport == transport), None)


def _family(kind: str, *protocols: tuple[str, Transport, str, str, Demo]) -> Family:
    """A family whose modules sit where the recipe puts them."""
    return Family(
        kind,
        f"busgate.schemas.{kind}",
        tuple(
            WireProtocol(
                name,
                kind,
                transport,
                f"busgate.codecs.{name}",
                f"busgate.gateway.drivers.{name}:{driver}",
                f"busgate.gateway.sim.{simulator}",
                demo,
            )
            for name, transport, driver, simulator, demo in protocols
        ),
    )


FAMILIES: dict[str, Family] = {}


def register(family: Family) -> None:
    """Add a family (before the schemas that derive from the registry are imported: their
    types are made once). Kind and protocol names are unique."""
    taken = set(PROTOCOLS) | set(FAMILIES)
    clashes = sorted(({family.kind} | {p.name for p in family.protocols}) & taken)
    if clashes:
        raise ValueError(f"family {family.kind}: {', '.join(clashes)} already registered")
    if len({p.transport for p in family.protocols}) != len(family.protocols):
        raise ValueError(f"family {family.kind}: one protocol per transport")
    FAMILIES[family.kind] = family
    PROTOCOLS.update((p.name, p) for p in family.protocols)


#: Every protocol of every family, by name.
PROTOCOLS: dict[str, WireProtocol] = {}

for _entry in (
    _family(
        "inspire_la",
        ("inspire_la", "serial", "InspireLaDriver", "inspire_la:InspireLaDevice",
         Demo("uart0", (("la1", 1), ("la2", 2), ("la3", 3)))),
    ),
    _family(
        "ds_servo",
        ("ds_servo", "serial", "DsServoDriver", "ds_servo:DsServoDevice",
         Demo("uart1", (("servo1", 1), ("servo2", 2)))),
    ),
    _family(
        "zlac706",
        ("zlac706_can", "can", "Zlac706CanDriver", "zlac706:Zlac706CanDevice",
         Demo("can0", (("wheel", 1),))),
        ("zlac706_rs232", "serial", "Zlac706Rs232Driver", "zlac706:Zlac706Rs232Device",
         Demo("rs232", (("drive", 1),))),
    ),
):  # fmt: skip
    register(_entry)


def kinds() -> tuple[str, ...]:
    """Every device kind, in registry order (for ``Literal`` types)."""
    return tuple(FAMILIES)


def protocol_of(kind: str, transport: str) -> WireProtocol | None:
    """The protocol a device of ``kind`` speaks on ``transport`` (``None``: it cannot be there)."""
    family = FAMILIES.get(kind)
    return family.on(transport) if family else None
