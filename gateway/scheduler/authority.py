"""Who may send what to which device: every client request bound for a bus is authorised here.

A request is judged by what its frames do to the devices they address (a group frame's
targets, every device of the bus for a broadcast), never by the key it came through: a
``group_move`` sent on ``dev/la1/cmd`` is checked on every actuator it moves. Each bus has one
``Authority``, the one judge of every path: the bus thread asks it before planning a command;
the API before taking a follow target, accepting a trajectory play (and while it plays), ending
a stream or resetting an e-stop (``judge``: one device by name, by what the request does to
it). Rules of this file:

1. An id that no device of the bus is configured with is refused (``unknown_device``), unless
   the frame only reads.
2. Reads and stops are never refused.
3. Anything else needs the claim of every device it addresses (``claimed``, naming the holder);
   a request that asks for it (``require_claim``) is refused unless its client holds that
   claim itself (``not_claimed``: the claim it took lapsed, or it never took one).
4. Motion to an e-stopped device is refused (``estopped``, naming the op that re-enables it).
5. What sets a device's position, speed or effort beyond its joint's limits is refused
   (``out_of_range``, naming the joint, the limit and the value): the positions, speeds and
   efforts its frames set (``Driver.setpoints``), judged by the joint of each device they
   address (``busgate.schemas.joints``). Follow streams are held within the limits instead
   (``gateway.scheduler.limiter``), and trajectory plays are checked whole before they start.
6. An id given to a device (``Driver.id_changes``: a ``set_id``, a raw write of the id, a
   factory reset) that another device of the bus has is refused (``out_of_range``): both
   would take every frame sent to it, and a claim on one would not keep the other still.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from busgate.errors import RefusedError
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import EVERY, Addressed, Driver, Effect, IdChange, Setpoint

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Holder:
    client: str
    until: float


class ClaimTable:
    """Who holds which device, until when. Thread-safe: zenoh threads and the bus thread use
    it. Every change is logged, for the journal; a holder's renewal (the SDK renews a claim
    every half of its TTL) only at debug level."""

    def __init__(self) -> None:
        self._holders: dict[str, Holder] = {}
        self._lock = threading.Lock()

    def claim(self, device: str, client: str, ttl_s: float, now: float) -> None:
        with self._lock:
            self._check(device, client, now)
            held = self._holders.get(device)
            renewed = held is not None and held.client == client and held.until > now
            self._holders[device] = Holder(client, now + ttl_s)
        if renewed:
            log.debug("device %s: the claim of %s renewed for %.1f s", device, client, ttl_s)
        else:
            log.info("device %s claimed by %s for %.1f s", device, client, ttl_s)

    def hold(self, device: str, client: str, ttl_s: float, now: float) -> bool:
        """``claim`` for a client that renews with every command it sends (the ROS face): only
        a new claim is logged; ``True`` when the claim is new."""
        with self._lock:
            self._check(device, client, now)
            new = device not in self._holders
            self._holders[device] = Holder(client, now + ttl_s)
        if new:
            log.info("device %s claimed by %s while its commands flow", device, client)
        return new

    def holder(self, device: str, now: float) -> str | None:
        """Who holds ``device`` now."""
        with self._lock:
            held = self._holders.get(device)
            return held.client if held is not None and held.until > now else None

    def release(self, device: str, client: str, now: float) -> bool:
        """``client``'s claim of ``device`` given back (``claimed`` when another holds it);
        whether there was one to give back."""
        with self._lock:
            self._check(device, client, now)  # a lapsed claim is gone after it
            held = self._holders.pop(device, None)
        if held is None:
            return False
        log.info("device %s released by %s", device, client)
        return True

    def check(self, device: str, client: str | None, now: float) -> None:
        """``claimed`` unless ``device`` is free or held by ``client``."""
        with self._lock:
            self._check(device, client, now)

    def require(self, device: str, client: str | None, now: float) -> None:
        """``not_claimed`` unless ``client`` holds ``device`` now (rule 3)."""
        with self._lock:
            self._check(device, client, now)
            if device not in self._holders:
                if client is None:  # a claim is a client's: one that names none holds none
                    raise RefusedError(
                        "not_claimed",
                        f"{device}: the command asks for its client's claim and names no "
                        'client: send "client" with it',
                    )
                raise RefusedError(
                    "not_claimed",
                    f"{device} is not claimed by {client!r}: its claim lapsed or was never "
                    "taken; claim it again",
                )

    def drop_client(self, client: str) -> list[str]:
        """Release every claim of ``client`` (it went away); the devices it held."""
        with self._lock:
            devices = [d for d, held in self._holders.items() if held.client == client]
            for device in devices:
                del self._holders[device]
        for device in devices:
            log.warning("device %s: claim of %s lost (client gone)", device, client)
        return devices

    def _check(self, device: str, client: str | None, now: float) -> None:
        held = self._holders.get(device)
        if held is None:
            return
        if held.until <= now:
            del self._holders[device]
            log.info("device %s: claim of %s lapsed", device, held.client)
            return
        if held.client != client:
            raise RefusedError(
                "claimed",
                f"{device} is claimed by {held.client!r} (its claim lapses in "
                f"{held.until - now:.1f} s unless renewed)",
            )


class Authority:
    """The one judge of one bus's requests (the rules at the top of this file)."""

    def __init__(
        self, bus: str, drivers: Mapping[str, Driver], clock: Callable[[], float] = now
    ) -> None:
        self.bus = bus
        self.drivers = drivers
        self.clock = clock
        self.claims = ClaimTable()

    def check(
        self,
        effects: Iterable[tuple[Addressed, Effect]],
        client: str | None,
        *,
        require_claim: bool = False,
    ) -> None:
        """Refuse (``RefusedError``) unless ``client`` may send frames with these effects."""
        moment = self.clock()
        judge = self.claims.require if require_claim else self.claims.check
        for ids, effect in effects:
            devices = self._devices(ids, effect)
            if effect <= Effect.STOP:
                continue
            for driver in devices:
                judge(driver.name, client, moment)
            if effect is Effect.MOTION:
                for driver in devices:
                    if driver.estopped:
                        raise driver.estopped_error()

    def addressed(
        self, effects: Iterable[tuple[Addressed, Effect]], effect: Effect = Effect.MOTION
    ) -> list[Driver]:
        """The devices frames with these effects do ``effect`` to (by default: move; checked
        by ``check`` before)."""
        return [
            driver for ids, done in effects if done is effect for driver in self._devices(ids, done)
        ]

    def check_limits(self, setpoints: Iterable[Setpoint]) -> None:
        """Refuse (``out_of_range``) what sets a device beyond its joint's limits (rule 5)."""
        by_id = self._by_id()
        for setpoint in setpoints:
            driver = by_id.get(setpoint.device_id)
            if driver is not None:  # an id no device has was refused by ``check``
                driver.joint.check(setpoint.quantity, setpoint.value)

    def check_ids(self, changes: Iterable[IdChange]) -> None:
        """Refuse (``out_of_range``) an id given to a device that another device of the bus
        has (rule 6)."""
        by_id = self._by_id()
        for change in changes:
            holder = by_id.get(change.new_id)
            if holder is not None and change.new_id != change.device_id:
                # A frame that gives an id addresses one device, by an id ``check`` knows.
                changing = by_id[change.device_id]
                raise RefusedError(
                    "out_of_range",
                    f"{changing.name} would take id {change.new_id}, {holder.name}'s on bus "
                    f"{self.bus}: two devices of one id both take every frame sent to it; give "
                    "it an id no device of the bus has",
                )

    def judge(
        self, device: str, effect: Effect, client: str | None, *, require_claim: bool = False
    ) -> None:
        """``check`` for a request that does ``effect`` to ``device`` alone, named: a follow
        target or a trajectory's tick moves it (``MOTION``), ending its stream or resetting
        its e-stop sets it (``SETTING``: the claim, never refused for an e-stop)."""
        driver = self.drivers[device]
        self.check([(frozenset({driver.device_id}), effect)], client, require_claim=require_claim)

    def holder(self, device: str) -> str | None:
        """Who holds ``device``'s claim now."""
        return self.claims.holder(device, self.clock())

    def _by_id(self) -> dict[int, Driver]:
        """Each device by its id, built at each check: ids change (set_id) on the bus thread."""
        return {driver.device_id: driver for driver in self.drivers.values()}

    def _devices(self, ids: Addressed, effect: Effect) -> list[Driver]:
        if ids is EVERY:
            return list(self.drivers.values())
        by_id = self._by_id()
        unknown = sorted(ids - by_id.keys())
        if unknown and effect is not Effect.READ:
            raise RefusedError(
                "unknown_device",
                f"no device of bus {self.bus} is configured with id {', '.join(map(str, unknown))}",
            )
        return [by_id[i] for i in sorted(ids) if i in by_id]
