"""busgate's Python SDK: every client program, the CLI and the dashboard are built on it.

>>> import busgate.client as bc
>>> bc.error_for("claimed").__name__, bc.error_for("out_of_range").code
('ClaimedError', 'out_of_range')

A program (against ``busgate demo``)::

    with bc.connect("tcp/127.0.0.1:7447", client_id="arm-ctl") as c:
        la1 = c.device("la1")
        print(la1.state().position)
        with la1.claim(ttl_s=2.0), la1.follow() as f:
            f.set(position=1200)

The same as coroutines: ``busgate.client.aio``. The rooms: ``core`` (the zenoh session, every
exchange as a future), ``base`` (what both faces share), ``sync`` and ``aio`` (the faces),
``claims`` (renewed in the background), ``feeds`` (telemetry), ``errors``, ``keys``, and
``zenoh_config`` (the session settings, shared with the daemon).
"""

from __future__ import annotations

from busgate.client import aio
from busgate.client.base import FleetDevice
from busgate.client.core import Answer, Answers
from busgate.client.errors import *  # noqa: F403 - one class per error code, made from the list
from busgate.client.errors import __all__ as _error_names
from busgate.client.sync import Bus, Claim, Client, Device, Follow, Trajectory, connect

__all__ = [
    "Answer",
    "Answers",
    "Bus",
    "Claim",
    "Client",
    "Device",
    "FleetDevice",
    "Follow",
    "Trajectory",
    "aio",
    "connect",
    *_error_names,
]
