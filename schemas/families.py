"""The device families busgate drives, each described once: the registry of their data.

Rules of this file:

1. A family is one ``Family`` entry in ``FAMILIES``; every table of kinds, protocols,
   transports, id ranges, timing, telemetry models and command schemas derives from it.
   Nothing else lists the families' data.
2. Wire facts (timing, device ids, whether frames carry an id) belong to the protocol's codec
   and are read from it (``TIMING``, ``DEVICE_IDS``, ``ADDRESSED``); a family's JSON side
   (commands, follow payload, telemetry) belongs to its schema module. The entry holds the
   codec module itself, imported here (an arrow the import-direction test sees), and names
   the schema module, in this room, to import on first use (the schema modules build their
   types on the config's names, and the config is built on this registry).
3. What drives and simulates a protocol is the gateway's, registered beside the drivers and
   the simulators (``busgate.gateway.drivers.families.DRIVERS``,
   ``busgate.gateway.sim.models.MODELS``, each one row per protocol, python-can's
   ``BACKENDS`` style); the devices the demo simulates are the demo's
   (``busgate.gateway.cli.demo``). This data layer names nothing above it.

Adding a family: its codec (``busgate.codecs.<protocol>``) and schema
(``busgate.schemas.<kind>``) modules and one ``Family`` here, then its driver and simulator
rows (docs/architecture.md has the recipe).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import ModuleType
from typing import Literal

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.timing import ProtocolTiming

Transport = Literal["serial", "can"]


@dataclass(frozen=True, slots=True)
class WireProtocol:
    """One wire protocol of a family: its name, its family's kind, the transport its frames
    travel on, and its codec module."""

    name: str
    kind: str
    transport: Transport
    codec: ModuleType

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
    protocols: tuple[WireProtocol, ...]
    #: The schema module's name (rule 2): ``busgate.schemas.<kind>`` unless given.
    schema_module: str = field(default="")

    @property
    def schema(self) -> ModuleType:
        return importlib.import_module(self.schema_module or f"busgate.schemas.{self.kind}")

    def on(self, transport: str) -> WireProtocol | None:
        """The family's protocol on ``transport``, if it has one."""
        return next((p for p in self.protocols if p.transport == transport), None)


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
    Family("inspire_la", (WireProtocol("inspire_la", "inspire_la", "serial", inspire_la),)),
    Family("ds_servo", (WireProtocol("ds_servo", "ds_servo", "serial", ds_servo),)),
    Family(
        "zlac706",
        (
            WireProtocol("zlac706_can", "zlac706", "can", zlac706_can),
            WireProtocol("zlac706_rs232", "zlac706", "serial", zlac706_rs232),
        ),
    ),
):
    register(_entry)


def kinds() -> tuple[str, ...]:
    """Every device kind, in registry order (for ``Literal`` types)."""
    return tuple(FAMILIES)


def protocol_of(kind: str, transport: str) -> WireProtocol | None:
    """The protocol a device of ``kind`` speaks on ``transport`` (``None``: it cannot be there)."""
    family = FAMILIES.get(kind)
    return family.on(transport) if family else None
