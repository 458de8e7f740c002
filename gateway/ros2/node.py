"""A ROS 2 node on a zenoh session, as rmw_zenoh makes one: liveliness tokens that make the
node and its entities visible to ``ros2 node list`` and ``ros2 topic list``, publishers and
subscriptions on rmw_zenoh's data keys, and service servers as queryables.

Rules of this file:

1. Every entity declares its liveliness token before it carries data, and every sample,
   request and reply carries rmw_zenoh's attachment (sequence number, source time, GID):
   rmw_zenoh's subscribers drop samples without one.
2. What comes off the network never raises: a sample without rmw_zenoh's attachment (as
   rmw_zenoh's own subscriptions drop it: a plain zenoh put drives no joint) or whose payload
   is not the type's CDR is dropped, counted, and said in a warning at most once every
   ``DROPS_TOLD_EVERY_S`` an entity, each entity's count and last reason kept for the
   diagnostics (``drops``: a ROS user with a wrong type or a bad serializer learns why
   nothing moves); a request without its attachment or CDR is answered with
   an error reply and nothing is done, but for the e-stop's (``always=True``): an e-stop is
   carried out whatever its request looks like. Data is taken only on its entity's exact
   key, as rmw_zenoh's publishers and clients send it: a put or get on a wildcard key
   (``0/robot_joint_commands/**``, any peer's) reaches our subscriptions and queryables too,
   and is dropped (the e-stop's excepted, as a put on ``**`` stops on the zenoh API).
3. A subscription's samples wait for a thread of their own in an ``Intake`` (``bridge``
   rule 6: a flood of commands never holds zenoh's receiving threads, and with them an
   e-stop), which ``take_waiting`` empties for an e-stop. Its ring is sized for the largest
   sample the session takes (``MAX_RECEIVED``), not the largest the topic keeps: a sample's
   size is read only once its thread takes it, so a ring of a topic of small messages held
   a peer's 2 MiB samples by the hundred (an audit). Each is handled with the count of
   e-stops it was taken under (``intake`` rule 5). A service's handler runs on zenoh's
   receiving thread itself: the services are the e-stop and its reset, which must wait
   behind nothing, and keep the order a client called them in. Handlers are given decoded
   messages and must only hand work on (``bridge`` rule 1); a service's reply is sent when
   the handler's future is done, whichever thread that is.
4. Our publishers drop rather than block (congestion control DROP): a slow ROS subscriber
   never stalls the gateway. A publisher whose QoS is best effort is best effort on zenoh
   too, as rmw_zenoh maps it.
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import zenoh

from busgate.codecs.ros2 import messages, rmw_zenoh
from busgate.codecs.ros2.rmw_zenoh import EntityKind, Qos
from busgate.gateway.api.intake import Intake, backlog_for, take_puts
from busgate.gateway.bus.clock import now
from busgate.schemas.validation import shown
from busgate.schemas.zenoh_session import MAX_RECEIVED

log = logging.getLogger(__name__)

#: How often one entity's drops are said in the log at most (rule 2).
DROPS_TOLD_EVERY_S = 60.0

#: A service handler: the decoded request in, a future of the response out.
ServiceHandler = Callable[[dict[str, Any]], "Future[dict[str, Any]]"]


@dataclass(slots=True)
class Hushed:
    """A warning told each time it comes, but at most once every ``every_s``: the line after
    a quiet spell says how many were held back (a flood never fills the journal)."""

    every_s: float
    logger: logging.Logger = log  # whose lines they are
    told_at: float = -math.inf  # monotonic
    held: int = 0  # come since that line, not told

    def warn(self, line: str) -> bool:
        """``line`` told, or held back (``False``)."""
        moment = now()
        if moment - self.told_at < self.every_s:
            self.held += 1
            return False
        since = f" ({self.held} more since the last such line)" if self.held else ""
        self.told_at, self.held = moment, 0
        self.logger.warning("%s%s", line, since)
        return True


@dataclass(slots=True)
class Drops:
    """What one entity dropped (rule 2)."""

    count: int = 0
    last: str = ""  # the last one, in words
    told: Hushed = field(default_factory=lambda: Hushed(DROPS_TOLD_EVERY_S))


@dataclass(frozen=True, slots=True)
class NodeName:
    """Where the node is in the ROS graph."""

    domain_id: int
    namespace: str
    name: str
    distro: str

    def resolve(self, name: str) -> str:
        """A topic or service name, fully qualified (``~/x`` is under the node)."""
        return rmw_zenoh.resolve(name, self.namespace, self.name)


class Ros2Publisher:
    """One publisher: CDR of its type, with the attachment (rule 1)."""

    def __init__(self, publisher: zenoh.Publisher, type_name: str, gid: bytes) -> None:
        self._publisher = publisher
        self.type_name = type_name
        self._gid = gid
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()  # the sequence numbers go out in order
        self.published = 0

    def publish(self, message: dict[str, Any]) -> None:
        data = messages.encode(self.type_name, message)
        with self._lock:
            attachment = rmw_zenoh.attachment(next(self._sequence), time.time_ns(), self._gid)
            self._publisher.put(data, attachment=attachment)
            self.published += 1


class Ros2Node:
    """The node's entities on ``session`` (the rules above)."""

    def __init__(
        self, session: zenoh.Session, name: NodeName, estops: Callable[[], int] | None = None
    ) -> None:
        self.session = session
        self.name = name
        self._estops = estops  # the gateway's count, for what the subscriptions take
        self.zid = str(session.zid())
        #: entity → the samples and requests it dropped (rule 2): not its type's CDR, on a
        #: wildcard, without the attachment, over its size
        self.drops: dict[str, Drops] = {}
        self._entity_ids = itertools.count(1)
        self._keep: list[Any] = []
        self._intakes: list[Intake] = []  # rule 3
        self._node = rmw_zenoh.Node(name.domain_id, self.zid, 0, name.name, name.namespace)
        self._keep.append(session.liveliness().declare_token(rmw_zenoh.node_token(self._node)))

    def publisher(self, topic: str, type_name: str, qos: Qos) -> Ros2Publisher:
        key = self._announce(EntityKind.PUBLISHER, topic, type_name, qos)
        reliability = zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT
        publisher = self.session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.DROP, reliability=reliability
        )
        self._keep.append(publisher)
        return Ros2Publisher(publisher, type_name, rmw_zenoh.new_gid())

    def subscription(
        self,
        topic: str,
        type_name: str,
        qos: Qos,
        handler: Callable[[dict[str, Any]], None],
        max_bytes: int,
        max_count: int | None = None,
        *,
        newest_only: bool = False,
    ) -> None:
        """Each ``type_name`` message on ``topic``'s own key, of at most ``max_bytes`` and with
        no sequence longer than ``max_count``, decoded for ``handler``; anything else dropped
        (counted) before it is decoded, or as soon as a count is read. A message waits for its
        thread among at most ``backlog_for(MAX_RECEIVED)`` (rule 3); ``newest_only``: a message
        that comes while one waits takes its place, undecoded (where the handler keeps only
        the newest anyway: a burst of large messages costs two decodings, not one each)."""
        key = self._announce(EntityKind.SUBSCRIPTION, topic, type_name, qos)

        def received(sample: zenoh.Sample) -> None:
            if str(sample.key_expr) != key:
                self._drop(topic, f"a sample on {shown(str(sample.key_expr))}, not the topic's key")
                return
            attached = sample.attachment
            if rmw_zenoh.read_attachment(None if attached is None else attached.to_bytes()) is None:
                self._drop(topic, "a sample without rmw_zenoh's attachment")
                return
            payload = sample.payload.to_bytes()
            if len(payload) > max_bytes:
                self._drop(topic, f"a sample of {len(payload)} bytes, over {max_bytes}")
                return
            message = messages.decode(type_name, payload, max_count=max_count)
            if message is None:
                longest = "" if max_count is None else f" with no list over {max_count}"
                self._drop(topic, f"a sample that is not {type_name} CDR{longest}")
                return
            handler(message)

        thread = f"ros2 {shown(topic)}"
        backlog = 1 if newest_only else backlog_for(MAX_RECEIVED)
        self._intakes.append(take_puts(self.session, key, received, thread, backlog, self._estops))

    def service(
        self, name: str, type_name: str, handler: ServiceHandler, *, always: bool = False
    ) -> None:
        """A service server of ``type_name`` (``std_srvs/srv/Trigger``); with ``always`` a
        request is carried out even when it is not well formed (rule 2: the e-stop)."""
        key = self._announce(EntityKind.SERVICE_SERVER, name, type_name, rmw_zenoh.SERVICES)
        request_type, response_type = f"{type_name}_Request", f"{type_name}_Response"
        gid = rmw_zenoh.new_gid()

        def asked(query: zenoh.Query) -> None:
            if str(query.key_expr) != key and not always:
                where = shown(str(query.key_expr))
                self._drop(name, f"a request on {where}, not the service's key")
                query.drop()
                return
            raw = query.payload.to_bytes() if query.payload is not None else b""
            request = messages.decode(request_type, raw)
            sent = rmw_zenoh.read_attachment(
                query.attachment.to_bytes() if query.attachment is not None else None
            )
            if (request is None or sent is None) and not always:
                self._drop(name, f"a request without its attachment or not {request_type}")
                query.reply_err(f"not a {type_name} request with rmw_zenoh's attachment")
                query.drop()
                return
            sequence, client = (sent.sequence, sent.gid) if sent is not None else (0, gid)

            def reply(done: Future) -> None:
                try:
                    attachment = rmw_zenoh.attachment(sequence, time.time_ns(), client)
                    payload = messages.encode(response_type, done.result())
                    query.reply(key, payload, attachment=attachment)
                except Exception:  # the query may have gone: nothing more to do for it
                    log.exception("%s: the reply could not be sent", name)
                finally:
                    query.drop()

            handler(request or {}).add_done_callback(reply)

        on_receiving_thread = zenoh.handlers.Callback(asked, indirect=False)  # rule 3
        self._keep.append(self.session.declare_queryable(key, on_receiving_thread, complete=True))

    def take_waiting(self) -> int:
        """The subscriptions' samples still waiting for their threads, dropped (rule 3): how
        many."""
        return sum(len(intake.take_waiting()) for intake in self._intakes)

    def close(self) -> None:
        """Undeclare everything (the tokens go: the node leaves the graph)."""
        for intake in self._intakes:
            intake.close()
        for entity in reversed(self._keep):
            entity.undeclare()
        self._keep.clear()
        for intake in self._intakes:
            intake.join()

    def _announce(self, kind: EntityKind, name: str, type_name: str, qos: Qos) -> str:
        """The entity's liveliness token (rule 1); its data key."""
        full, distro = self.name.resolve(name), self.name.distro
        token = rmw_zenoh.entity_token(
            self._node, next(self._entity_ids), kind, full, type_name, distro, qos
        )
        self._keep.append(self.session.liveliness().declare_token(token))
        return rmw_zenoh.data_key(self.name.domain_id, full, type_name, distro)

    def _drop(self, entity: str, what: str) -> None:
        """``what`` came to ``entity`` and was dropped: counted, and told (rule 2)."""
        drops = self.drops.setdefault(entity, Drops())
        drops.count += 1
        drops.last = what
        if not drops.told.warn(f"ros2: {entity}: dropped {what}"):
            log.debug("ros2: %s: dropped %s", entity, what)
