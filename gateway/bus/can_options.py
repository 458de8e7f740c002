"""python-can's options and interfaces as a config names them: whether this host's python-can
knows a bus's ``interface``, and which of its ``options`` the bus takes by no name (most
likely misspelt). ``busgate check-config`` warns of both, and ``busgate run`` refuses an
unknown interface; the CAN owner itself never asks."""

from __future__ import annotations

import importlib
import inspect
import logging
import re
import sys
from collections.abc import Iterable

import can
from can.typechecking import BitTimingDict, BitTimingFdDict

#: The options python-can takes for every interface besides a bus class's own parameters
#: (``unnamed_options``): those its configuration step reads (``can.util``) and a bit
#: timing's, which it makes a ``timing`` of.
PYTHON_CAN_KEYS = frozenset(
    {"fd", "data_bitrate", "port", "state", "timing",
     *BitTimingDict.__annotations__, *BitTimingFdDict.__annotations__}
)  # fmt: skip
#: A key a bus's module reads from its ``**kwargs`` (``kwargs.get("fd")``, ``kwargs["x"]``).
KWARGS_READ = re.compile(r"""kwargs(?:\.get\(|\.pop\(|\[)\s*["'](\w+)["']""")


def unknown_interface(interface: str) -> str | None:
    """Why a bus on ``interface`` could never open here (python-can knows no such interface:
    neither its own nor a plugin installed on this host), ``None`` when it knows it."""
    if interface in can.interfaces.VALID_INTERFACES:
        return None
    known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
    return f"python-can has no interface {interface!r} on this host (it has {known})"


def unnamed_options(interface: str, options: Iterable[str]) -> list[str]:
    """Those of ``options`` that python-can's bus for ``interface`` takes by no name it gives:
    not a parameter of the class (nor of ``can.Bus``, nor ``can.BusABC``, which every bus
    takes), not one of python-can's own for every interface (``PYTHON_CAN_KEYS``), and not a
    key the class's module reads from its ``**kwargs`` (``kwargs.get("fd")``, as pcan's does):
    most likely misspelt, as ``**kwargs`` takes any name in silence. None when the class
    cannot be loaded here; python-can's warnings as it loads one (``Kvaser canlib is
    unavailable.``) are kept quiet meanwhile: opening the bus tells what it lacks."""
    python_can_log = logging.getLogger("can")
    level = python_can_log.level
    python_can_log.setLevel(logging.ERROR)
    try:
        module, name = can.interfaces.BACKENDS[interface]
        bus_class = getattr(importlib.import_module(module), name)
        named = {
            parameter.name
            for function in (bus_class.__init__, can.BusABC.__init__, can.Bus)
            for parameter in inspect.signature(function).parameters.values()
            if parameter.kind not in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD)
        }
        named.update(KWARGS_READ.findall(inspect.getsource(sys.modules[bus_class.__module__])))
    except Exception:  # a plugin's module may raise anything as it loads
        return []
    finally:
        python_can_log.setLevel(level)
    return [key for key in options if key not in named and key not in PYTHON_CAN_KEYS]
