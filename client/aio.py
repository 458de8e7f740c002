"""The SDK's asyncio face: the same surface as ``busgate.client`` (``sync.py``), as
coroutines, async iterators and async context managers.

Its methods are the ones both faces share (``surface.py``, ``devices.py``, ``trajectories.py``,
``bases.py``), each run awaiting (``faces.Awaiting``). zenoh-python has no asyncio API: its
callbacks settle ``concurrent.futures.Future``s on zenoh's threads, and
``asyncio.wrap_future`` hands each result to the loop with ``call_soon_threadsafe``; samples
reach the loop the same way. Nothing here blocks the loop: opening and closing the session,
the only blocking zenoh calls, run in a worker thread. What is this face's own: its classes,
``connect`` (awaited, or an ``async with``), and the ``async with`` blocks of a claim, a
follow stream, a base's drive stream and a trajectory.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Generator
from typing import Any, Self

from busgate.client.bases import DriveStreamBase, MobileBase
from busgate.client.devices import BusBase, ClaimBase, DeviceBase, FollowBase, StreamBase
from busgate.client.faces import Awaiting, init_taking
from busgate.client.joints import JointBase, JointFollowBase
from busgate.client.steps import arun
from busgate.client.surface import ClientBase, connecting
from busgate.client.trajectories import Handle


class connect:
    """``async with bc.aio.connect(endpoints, client_id=…) as c``, or ``c = await
    bc.aio.connect(…)`` and ``await c.close()``; the options are ``bc.connect``'s."""

    @init_taking(connecting)
    def __init__(self, *args: Any, **options: Any) -> None:
        inspect.signature(connecting).bind(*args, **options)  # a wrong option fails here
        self._connecting = functools.partial(connecting, *args, **options)
        self._client: Client | None = None

    async def _open(self) -> Client:
        return Client(await arun(self._connecting()))

    def __await__(self) -> Generator[Any, None, Client]:
        return self._open().__await__()

    async def __aenter__(self) -> Client:
        self._client = await self._open()
        return self._client

    async def __aexit__(self, *exc_info: object) -> None:
        if self._client is not None:
            await self._client.close()


class Claim(Awaiting, ClaimBase):
    """``async with device.claim(ttl_s)`` (or a base's): as ``busgate.client.Claim``."""

    async def __aenter__(self) -> Claim:
        return await arun(self._taken())

    async def __aexit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        await arun(self._given_back(kind))


class _Stream(Awaiting, StreamBase):
    """A follow stream's ``async with`` block: opened on entry, ended on exit."""

    async def __aenter__(self) -> Self:
        return self._opened()

    async def __aexit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        await arun(self._ended(kind))


class Follow(_Stream, FollowBase):
    """``async with device.follow() as f``: ``f.set(…)`` does not wait (a put)."""


class JointFollow(_Stream, JointFollowBase):
    """``async with joint.follow() as f``: ``f.set(value)`` does not wait (a put)."""


class Joint(Awaiting, JointBase["Device", JointFollow]):
    """One device as a joint, for asyncio (``busgate.client.Joint``'s methods)."""

    _JointFollow = JointFollow


class Device(Awaiting, DeviceBase[Claim, Follow, Joint]):
    """One device of one gateway, for asyncio (``busgate.client.Device``'s methods)."""

    _Claim, _Follow, _Joint = Claim, Follow, Joint


class Bus(Awaiting, BusBase):
    """One bus of one gateway, for asyncio."""


class Trajectory(Awaiting, Handle):
    """A trajectory a gateway plays (``await c.play(...)``), for asyncio: as
    ``busgate.client.Trajectory``."""

    async def __aenter__(self) -> Trajectory:
        return self

    async def __aexit__(self, exc_type: object, *exc_info: object) -> None:
        self._left(failed=exc_type is not None)


class DriveStream(_Stream, DriveStreamBase):
    """``async with base.drive_stream() as d``: ``d.send(linear, angular)`` does not wait (a
    put); the base is stopped when the block exits."""


class Base(Awaiting, MobileBase[Claim, DriveStream]):
    """One base of one gateway, for asyncio (``busgate.client.Base``'s methods)."""

    _Claim, _DriveStream = Claim, DriveStream


class Client(Awaiting, ClientBase[Device, Bus, Trajectory, Joint, Base]):
    """One program's connection to a fleet of gateways, for asyncio."""

    _Device, _Bus, _Trajectory, _Base = Device, Bus, Trajectory, Base
