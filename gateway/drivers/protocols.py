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
    driver_name: str
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

    @property
    def driver_class(self) -> type:
        """The gateway driver class of a device on this protocol."""
        return getattr(self.driver, self.driver_name)


PROTOCOLS: dict[str, Protocol] = {
    p.name: p
    for p in (
        Protocol("inspire_la", "inspire_la", addressed=True, driver_name="InspireLaDriver"),
        Protocol("ds_servo", "ds_servo", addressed=True, driver_name="DsServoDriver"),
        Protocol(
            "zlac706_can", "zlac706", addressed=True, driver_name="Zlac706CanDriver", can=True
        ),
        Protocol("zlac706_rs232", "zlac706", addressed=False, driver_name="Zlac706Rs232Driver"),
    )
}
