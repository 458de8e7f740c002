"""Which device model serves which protocol, and how a set of them is made.

Rules of this file:

1. ``MODELS`` is the one table of simulator models: a row per protocol of the registry
   (``busgate.schemas.families``), the class itself beside the models, as the drivers'
   ``DRIVERS`` is beside the drivers. A model missing what the servers call is refused with a
   ``FamilyError`` naming it.
2. Model classes take ``(device_id, **options)``; options a model does not know are refused,
   so a typo on the command line is an error rather than a silently ignored flag.
"""

from __future__ import annotations

from collections.abc import Iterable

from busgate.errors import CommandError, FamilyError
from busgate.gateway.drivers.families import SIMULATOR_PARTS, require
from busgate.gateway.sim.device import SimDevice
from busgate.gateway.sim.ds_servo import DsServoDevice
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.zlac706 import Zlac706CanDevice, Zlac706Rs232Device

#: Each protocol's simulator model (rule 1).
MODELS: dict[str, type] = {
    "inspire_la": InspireLaDevice,
    "ds_servo": DsServoDevice,
    "zlac706_can": Zlac706CanDevice,
    "zlac706_rs232": Zlac706Rs232Device,
}


def model_class(protocol: str) -> type:
    """The simulator model of ``protocol``, checked for what the servers call (a
    ``FamilyError`` names what it lacks)."""
    owner = f"protocol {protocol}"
    cls = MODELS.get(protocol)
    if cls is None:
        raise FamilyError(f"{owner}: no simulator model is registered for it (MODELS)")
    require(cls, SIMULATOR_PARTS, f"simulator {cls.__qualname__}", owner)
    return cls


def make_devices(protocol: str, ids: Iterable[int], **options: object) -> list[SimDevice]:
    """One simulated device per id, all of ``protocol``'s model; an id given twice is
    refused (``CommandError``): both devices would answer every frame sent to it."""
    ids = list(ids)
    for device_id in ids:
        if ids.count(device_id) > 1:
            raise CommandError(f"id {device_id} is given twice: one device an id")
    cls = model_class(protocol)
    return [cls(device_id, **options) for device_id in ids]
