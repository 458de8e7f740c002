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
exchange as a future) and ``messages`` (what the exchanges carry); ``base`` (what both faces
share below their methods); ``surface``, ``devices`` and ``trajectories`` (every method of
both faces, written once as the steps it waits for: ``steps``), made each face's methods by
``faces``; ``joints`` (a device as a joint, in SI); ``bases`` (a gateway's bases: two wheels
driven as one); ``sync`` and ``aio`` (the faces: their
classes and blocks); ``claims`` (renewed in the background), ``feeds`` (telemetry),
``errors`` and ``keys``. The zenoh session settings
are ``busgate.schemas.zenoh_session``'s, shared with the daemon (``zenoh_config`` still names
them for scripts of earlier releases).
"""

from __future__ import annotations

from busgate.client import aio
from busgate.client.base import FleetDevice
from busgate.client.errors import *  # noqa: F403 - one class per error code, made from the list
from busgate.client.errors import __all__ as _error_names
from busgate.client.messages import (
    Answer,
    Answers,
    JointInfo,
    JointReading,
    JointsMessage,
    JointState,
    Odometry,
)
from busgate.client.sync import (
    Base,
    Bus,
    Claim,
    Client,
    Device,
    DriveStream,
    Follow,
    Joint,
    JointFollow,
    Trajectory,
    connect,
)

__all__ = [
    "Answer",
    "Answers",
    "Base",
    "Bus",
    "Claim",
    "Client",
    "Device",
    "DriveStream",
    "FleetDevice",
    "Follow",
    "Joint",
    "JointFollow",
    "JointInfo",
    "JointReading",
    "JointState",
    "JointsMessage",
    "Odometry",
    "Trajectory",
    "aio",
    "connect",
    *_error_names,
]
