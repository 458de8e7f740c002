"""The registry of wire protocols: for each, its codec, its command schema and its driver.

The CLI and (later) the daemon look protocols up here by name, so adding a protocol is one
row. Modules are imported on first use to keep ``busgate --help`` fast.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType


@dataclass(frozen=True, slots=True)
class Protocol:
    """One wire protocol and the device kind that speaks it.

    ``addressed`` says whether frames carry a device id (``--id``); ``can`` whether frames are
    CAN frames rather than a byte stream.
    """

    name: str
    kind: str
    addressed: bool
    can: bool = False

    @property
    def codec(self) -> ModuleType:
        return importlib.import_module(f"busgate.codecs.{self.name}")

    @property
    def schema(self) -> ModuleType:
        return importlib.import_module(f"busgate.schemas.{self.kind}")

    @property
    def driver(self) -> ModuleType:
        return importlib.import_module(f"busgate.gateway.drivers.{self.name}")


PROTOCOLS: dict[str, Protocol] = {
    p.name: p
    for p in (
        Protocol("inspire_la", kind="inspire_la", addressed=True),
        Protocol("ds_servo", kind="ds_servo", addressed=True),
        Protocol("zlac706_can", kind="zlac706", addressed=True, can=True),
        Protocol("zlac706_rs232", kind="zlac706", addressed=False),
    )
}
