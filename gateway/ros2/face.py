"""busgate in ROS 2: a node on the gateway's own zenoh session, in rmw_zenoh's wire format, so
ros2_control's topic-based system, MoveIt and the joint trajectory controller drive the
gateway's joints with no bridge.

Rules of this file:

1. Joint states out: every joint by its joint name, in SI (NaN where unknown), stamped with
   the newest reading's time, each time the gateway's joints message goes out (when joints
   were read again, at most at the fastest poll rate).
2. Joint commands in act under the ``client`` of ``[ros2]`` like any client's: each commanded
   joint is held by that client while its commands come (``CLAIM_TTL_S`` from the last, or
   twice ``command_timeout_s`` when that is longer) and
   ramps to its target within its limits (``GatewayApi.ramp_to``); a refusal (claimed by
   another client, e-stopped, a trajectory playing) moves nothing and is said once in the log
   (once a second at most, whatever its words) and in the diagnostics until a command for that
   joint is taken again. A refused message that names no joint of this gateway (no names, or
   only names no joint has) is shown in the commands' status instead, until a command or a
   trajectory is taken, and each such refusal is told, a line a second at most (``Hushed``).
   A velocity joint without a command for ``command_timeout_s`` ramps to 0.
3. A trajectory goes to the gateway's trajectory lane as the trajectory key's command would,
   under the same client; its refusal is shown in the joints' diagnostics, or the commands'
   status when it names none of them (but for an empty one's when nothing plays: the
   controller's way to stop asks nothing that was refused), and each refusal is told, saying
   it plays nothing, a line a second at most (``Hushed``). One message is on the key at a
   time, so they are carried out in the order they came (an empty one right behind a play
   cancels that play, never a play before it); of those that came while one was on the key
   only the newest is sent next, as a topic wants.
4. Each base takes ``cmd_vel`` and publishes ``odom`` and ``tf`` (``ros2.bases``).
   The e-stop service stops every bus whatever its request looks like; the reset service
   brings them back as ``<gw>/estop/reset`` does. ``~/estopped`` is published on change and
   once a second; ``/diagnostics`` once a second.
5. Handlers hand over (``bridge`` rule 1); the periodic work runs on the loop's thread.
   A command message is taken apart on its subscription's thread (``node`` rule 3) and its
   targets handed to the loop, each joint's latest alone (``_due``). Any e-stop, the zenoh
   API's or the service's, drops what is due, the messages still waiting for their threads
   and the trajectory message waiting for its turn; and what a message was taken under (the
   gateway's count of e-stops, ``intake`` rule 5) goes with it, so that one being read or
   handed on when the e-stop came is refused too: nothing sent before it moves a joint after
   the reset. Nothing of a name no joint has is kept beyond ``Commands``' few,
   nor logged but cut (``shown``).
6. The face never ends the gateway: a failure of its periodic work or of a publication (a
   bug) is logged once, with its traceback, and the gateway serves on.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import asdict
from typing import Any

from busgate.codecs.ros2 import rmw_zenoh
from busgate.codecs.ros2.messages import time_of
from busgate.errors import RefusedError
from busgate.gateway.api.bridge import ZenohBridge, ignored
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.api.put_reports import not_reset_said
from busgate.gateway.api.taken import estops_when_taken
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.ros2.bases import BaseTopics
from busgate.gateway.ros2.commands import Commands, JointRef, Target
from busgate.gateway.ros2.diagnostics import BusHealth, Dropped, JointHealth, diagnostic_array
from busgate.gateway.ros2.node import Hushed, NodeName, Ros2Node
from busgate.gateway.ros2.trajectory import trajectory_command
from busgate.schemas.encoding import message_json
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.replies import error_reply
from busgate.schemas.ros2 import Ros2Section
from busgate.schemas.trajectory import MAX_TRAJECTORY_PAYLOAD, MAX_TRAJECTORY_POINTS
from busgate.schemas.validation import shown

log = logging.getLogger(__name__)

#: The largest play a trajectory message makes, in bytes of JSON: its CDR is at most
#: ``MAX_TRAJECTORY_PAYLOAD``, where each value takes 8 bytes and its JSON at most some 26
#: (held to the trajectory key's megabyte, a message of 9,000 points of two joints, well
#: within both of its own limits, was refused).
PLAY_JSON_MAX = 4 * MAX_TRAJECTORY_PAYLOAD

#: How long a joint stays held by the face after its last command (rule 2): long enough that
#: a controller's steady stream keeps it, short enough that another client gets it soon
#: after ROS stops commanding.
CLAIM_TTL_S = 2.0
#: How often the periodic work looks at the time (velocity timeouts, the e-stop state).
TICK_S = 0.005
EVERY_SECOND_S = 1.0
#: A joint's refusals are logged at most this often (rule 2), however their words change;
#: and so are the refusals no joint's line tells, each kind's (``Hushed``).
REFUSAL_TOLD_EVERY_S = 1.0
#: A refusal is logged up to this many characters: whole, why included (its names are cut).
REFUSAL_SHOWN_CHARS = 300

JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
BOOL = "std_msgs/msg/Bool"
TRIGGER = "std_srvs/srv/Trigger"


class Ros2Face:
    """The gateway's ROS 2 node (the rules above)."""

    def __init__(self, section: Ros2Section, api: GatewayApi, bridge: ZenohBridge) -> None:
        self.section = section
        self.api = api
        self.bridge = bridge
        self.node_name = section.node_of(api.name)
        self.joints = {
            driver.joint.name: JointRef(driver.joint.name, device, driver.joint.type)
            for device, (_, driver) in api.devices.items()
        }
        self.commands = Commands(self.joints, section.command_timeout_s)
        #: A velocity joint is held past its command timeout (its stop is the face's).
        self._claim_ttl_s = max(CLAIM_TTL_S, 2 * section.command_timeout_s)
        self._commands_lock = threading.Lock()
        self._refusals: dict[str, str] = {}  # joint → its last refused command (rule 2)
        self._refusal_told: dict[str, float] = {}  # joint → when its last refusal was logged
        #: The last refused message that named no joint of this gateway, until one is taken.
        self._nameless_refusal: str | None = None
        #: Commands that name no joint of this gateway, refused; trajectories refused.
        self._nameless_told = Hushed(REFUSAL_TOLD_EVERY_S, log)
        self._trajectories_told = Hushed(REFUSAL_TOLD_EVERY_S, log)
        #: The trajectory message on the trajectory key, and the newest come since (rule 3).
        self._trajectory_lock = threading.Lock()
        self._trajectory_sent = False
        #: (joint names, payload, a cancel, the e-stops counted when it came)
        self._trajectory_next: tuple[list[str], bytes, bool, int] | None = None
        #: joint → its latest command not handed on, and the e-stops counted when it came
        self._due: dict[str, tuple[Target, int]] = {}
        self._handing_on = False  # the loop is due to hand on ``_due``
        self._errors_seen: dict[str, int] = {}  # bus → timeouts and bad checksums so far
        self._drops_seen: dict[str, int] = {}  # topic or service → drops told in /diagnostics
        self._node: Ros2Node | None = None
        self._estopped: bool | None = None
        self._failed: set[str] = set()  # what failed and was told (rule 6)

    # -- lifetime ---------------------------------------------------------------------------

    def open(self) -> None:
        """The node and its entities, on the bridge's open session."""
        section = self.section
        self._node = node = Ros2Node(
            self.bridge.session,
            NodeName(section.domain_id, section.namespace, self.node_name, section.distro),
            estops=lambda: self.api.estops,
        )
        self._states = node.publisher(section.joint_states, JOINT_STATE, rmw_zenoh.SENSOR_DATA)
        self._diagnostics = node.publisher(section.diagnostics, DIAGNOSTIC_ARRAY, rmw_zenoh.DEFAULT)
        self._estop_state = node.publisher(section.estopped, BOOL, rmw_zenoh.DEFAULT)
        node.subscription(
            section.joint_commands, JOINT_STATE, rmw_zenoh.COMMANDS, self._command, MAX_PAYLOAD
        )
        node.subscription(
            section.joint_trajectory,
            JOINT_TRAJECTORY,
            rmw_zenoh.DEFAULT,
            self._trajectory,
            MAX_TRAJECTORY_PAYLOAD,
            MAX_TRAJECTORY_POINTS,  # 40,000 empty points fit a megabyte, and took 0.4 s to read
            newest_only=True,  # rule 3: of those that come meanwhile only the newest goes next
        )
        node.service(section.estop, TRIGGER, self._estop, always=True)
        node.service(section.reset_estop, TRIGGER, self._reset_estop)
        self.bridge.at_estop.append(self._forget_before_estop)  # any e-stop's (rule 5)
        self.bridge.on_joints = self.publish_joints
        if self.bridge.bases.bases:
            topics = BaseTopics(node, section, self.bridge.bases)
            self.bridge.on_odometry = lambda name, odometry: self._guarded(
                "publishing odometry", lambda: topics.odometry(name, odometry)
            )
        log.info(
            "ROS 2 node %s up (domain %d, %s definitions): joint states on %s, commands on %s",
            node.name.resolve(self.node_name),
            section.domain_id,
            section.distro,
            node.name.resolve(section.joint_states),
            node.name.resolve(section.joint_commands),
        )

    def close(self) -> None:
        self.bridge.on_joints = self.bridge.on_odometry = ignored
        if self._forget_before_estop in self.bridge.at_estop:
            self.bridge.at_estop.remove(self._forget_before_estop)
        node, self._node = self._node, None
        if node is not None:
            node.close()

    async def run(self, stop: asyncio.Event) -> None:
        """The periodic work (rules 2 and 4), on the loop's thread."""
        next_second = 0.0
        while not stop.is_set():
            moment = now()
            every_second = moment >= next_second
            if every_second:
                next_second = moment + EVERY_SECOND_S
            self._guarded("the periodic work", functools.partial(self._round, moment, every_second))
            await asyncio.sleep(TICK_S)

    def _round(self, moment: float, every_second: bool) -> None:
        self._stop_silent_joints(moment)
        estopped = self._gateway_estopped()
        if estopped != self._estopped or every_second:
            self._estopped = estopped
            self._estop_state.publish({"data": estopped})
        if every_second:
            self._diagnostics.publish(self.diagnostics())

    def _guarded(self, what: str, work: Callable[[], None]) -> None:
        """``work``, whose failure (a bug) is logged once and never ends the gateway (rule 6)."""
        try:
            work()
        except Exception:
            if what not in self._failed:
                self._failed.add(what)
                log.exception("ros2: %s failed (told once; the gateway goes on)", what)

    # -- out --------------------------------------------------------------------------------

    def publish_joints(self, joints: dict[str, Any]) -> None:
        """The gateway's joints message as a JointState (rule 1)."""
        self._guarded("publishing joint states", lambda: self._publish_joints(joints))

    def _publish_joints(self, joints: dict[str, Any]) -> None:
        entries = joints["joints"]
        read = [entry["ts"] for entry in entries if entry["ts"] is not None]
        self._states.publish(
            {
                "header": {"stamp": time_of(max(read) if read else joints["ts"]), "frame_id": ""},
                "name": [entry["name"] for entry in entries],
                "position": [_number(entry["position"]) for entry in entries],
                "velocity": [_number(entry["velocity"]) for entry in entries],
                "effort": [_number(entry["effort"]) for entry in entries],
            }
        )

    def diagnostics(self) -> dict[str, Any]:
        """The DiagnosticArray of this moment."""
        joints = []
        for joint in self.joints.values():
            runner, driver = self.api.devices[joint.device]
            joints.append(
                JointHealth(
                    joint=joint.name,
                    device=joint.device,
                    hardware_id=f"{driver.kind} id {driver.device_id} on bus {runner.name}",
                    state=runner.states.get(joint.device),
                    claimed_by=runner.authority.holder(joint.device),
                    refusal=self._refusals.get(joint.name),
                )
            )
        buses = []
        for name, runner in self.api.runners.items():
            stats = asdict(runner.statistics())
            errors = stats["timeouts"] + stats["checksum_errors"]
            new_errors = errors - self._errors_seen.get(name, errors)
            self._errors_seen[name] = errors
            buses.append(BusHealth(name, runner.owner.is_open, stats, new_errors))
        with self._commands_lock:  # zenoh's threads add to it
            unknown = set(self.commands.unknown)
        stamp = time_of(time.time())
        return diagnostic_array(
            self.node_name,
            stamp,
            joints,
            buses,
            unknown,
            self._dropped_since_last(),
            self._nameless_refusal,
        )

    def _dropped_since_last(self) -> list[Dropped]:
        """What each of the node's topics and services dropped, and how much of it since the
        last status."""
        node = self._node
        if node is None:  # not open: nothing came
            return []
        dropped = []
        for entity, drops in list(node.drops.items()):  # zenoh's threads add to them
            count, last = drops.count, drops.last
            dropped.append(Dropped(entity, count, count - self._drops_seen.get(entity, 0), last))
            self._drops_seen[entity] = count
        return dropped

    # -- in (zenoh's threads: hand over only) -----------------------------------------------

    def _command(self, message: dict[str, Any]) -> None:
        came_under = estops_when_taken(self.api.estops)
        with self._commands_lock:
            taken = self.commands.take(message, now())
            self._due.update((t.joint.name, (t, came_under)) for t in taken.targets)
            hand_on = bool(self._due) and not self._handing_on
            self._handing_on |= hand_on
        if hand_on:
            self.bridge.call_soon(self._hand_on)
        _log_unknown(taken.unknown)
        if taken.refused is None:
            self._nameless_refusal = None
        else:
            self._refused(message.get("name") or [], taken.refused)

    def _hand_on(self) -> None:
        """The loop's thread: each joint's latest command, to its device (rule 5)."""
        with self._commands_lock:
            due, self._due, self._handing_on = self._due, {}, False
        for target, came_under in due.values():
            if came_under == self.api.estops:  # else sent before an e-stop: never carried out
                self._ramp(target.joint, target.follow_fields, target.taken_at)

    def _ramp(
        self, joint: JointRef, fields: dict[str, float], taken_at: float | None = None
    ) -> None:
        """``fields`` to ``joint``'s device, a command taken at ``taken_at`` (``None``: a
        timeout's stop, no command's)."""
        refused = self.api.ramp_to(joint.device, fields, self.section.client, self._claim_ttl_s)
        with self._commands_lock:  # a stop is due for a velocity joint that turns (rule 3)
            if refused is None:
                self.commands.carried_out(joint.name)
            else:
                self.commands.refused(joint.name, taken_at)
        if refused is None:
            self._refusals.pop(joint.name, None)
            return
        self._refused([joint.name], refused["error"]["message"])

    def _trajectory(self, message: dict[str, Any]) -> None:
        """Rule 3: one message at a time on the trajectory key, the newest of those that
        came meanwhile next."""
        names = message.get("joint_names") or []
        came_under = estops_when_taken(self.api.estops)  # before its decoding took its time
        try:
            command = trajectory_command(message, self.joints, self.section.client, time.time())
        except RefusedError as exc:
            with self._commands_lock:  # shown in the commands' status; its refusal tells them
                self.commands.newly_unknown(names)
            self._trajectory_refused(names, str(exc))
            return
        sent = (names, message_json(command), command["op"] == "cancel", came_under)
        with self._trajectory_lock:
            if self._trajectory_sent:
                self._trajectory_next = sent  # the one it replaces: never sent
                return
            self._trajectory_sent = True
        self._send_trajectory(*sent)

    def _send_trajectory(
        self, names: list[str], payload: bytes, cancel: bool, came_under: int
    ) -> None:
        answer = self.bridge.submit_trajectory(payload, came_under, PLAY_JSON_MAX)
        answer.add_done_callback(
            lambda done: self._trajectory_answered(names, done.result(), cancel)
        )

    def _trajectory_answered(self, names: list[str], reply: dict[str, Any], cancel: bool) -> None:
        if reply.get("ok") or cancel:  # a cancel is refused only when nothing plays (rule 3)
            for name in names:
                self._refusals.pop(name, None)
            self._nameless_refusal = None
        else:
            self._trajectory_refused(names, reply["error"]["message"])
        with self._trajectory_lock:
            following, self._trajectory_next = self._trajectory_next, None
            self._trajectory_sent = following is not None
        if following is not None:
            self._send_trajectory(*following)

    def _refused(self, names: Iterable[str], message: str) -> None:
        """A command's refusal: shown for each joint of this gateway it names, and told in
        one line for those not told so lately (rule 2); one that names none, shown and told
        as such (a name no joint has is ``Commands``' to tell, rule 5)."""
        moment = now()
        joints = self._joints_among(names)
        telling: list[str] = []
        for name in joints:
            told = self._refusal_told.get(name, -math.inf)
            if self._refusals.get(name) != message and moment - told >= REFUSAL_TOLD_EVERY_S:
                telling.append(name)
                self._refusal_told[name] = moment
        self._show_refusal(joints, message)
        if not joints:
            self._nameless_told.warn(
                "ros2: a command naming no joint of this gateway refused, nothing in it "
                f"moves: {shown(message, REFUSAL_SHOWN_CHARS)}"
            )
        elif telling:
            which = "joint" if len(telling) == 1 else "joints"
            log.warning(
                "ros2: command for %s %s refused: %s",
                which,
                ", ".join(telling),
                shown(message, REFUSAL_SHOWN_CHARS),
            )

    def _trajectory_refused(self, names: Iterable[str], why: str) -> None:
        """Shown as a command's refusal is; told each time, a line a second at most (rule 3)."""
        self._show_refusal(self._joints_among(names), f"trajectory: {why}")
        self._trajectories_told.warn(
            f"ros2: a trajectory refused, it plays nothing: {shown(why, REFUSAL_SHOWN_CHARS)}"
        )

    def _joints_among(self, names: Iterable[str]) -> list[str]:
        """The joints of this gateway ``names`` names, each once (a message may name a joint
        many times)."""
        return [name for name in dict.fromkeys(names) if name in self.joints]

    def _show_refusal(self, joints: list[str], message: str) -> None:
        """``message`` in the diagnostics of each of ``joints``, or of the commands when
        there are none (rules 2 and 3)."""
        for name in joints:
            self._refusals[name] = message
        if not joints:
            self._nameless_refusal = message

    def _estop(self, request: dict[str, Any]) -> Future:
        key = f"ros2 {self._resolve(self.section.estop)}"
        return _when_all(self.bridge.estop(self.section.client, key), "every bus stopped")

    def _forget_before_estop(self) -> None:
        """Any e-stop's (the bridge's ``at_estop``): what was sent before it, never carried
        out after it (rule 5)."""
        node = self._node
        if node is not None:
            node.take_waiting()
        with self._commands_lock:
            self._due.clear()
            self.commands.forget(self.joints)
        with self._trajectory_lock:
            self._trajectory_next = None

    def _reset_estop(self, request: dict[str, Any]) -> Future:
        reset, not_reset = self.bridge.estop_reset(self.section.client)
        return _when_all(reset, f"every bus reset{not_reset_said(not_reset)}")

    # -- the loop's thread -------------------------------------------------------------------

    def _stop_silent_joints(self, moment: float) -> None:
        with self._commands_lock:
            silent = self.commands.expired(moment)
        for joint in silent:
            log.info(
                "ros2: no command for velocity joint %s in %g s: ramping to 0",
                joint.name,
                self.section.command_timeout_s,
            )
            self.bridge.events.append(
                DeviceEvent(joint.device, "stream_stale", {"client": self.section.client})
            )
            self._ramp(joint, {"joint_velocity": 0.0})

    def _gateway_estopped(self) -> bool:
        return any(driver.estopped for _, driver in self.api.devices.values())

    def _resolve(self, name: str) -> str:
        return rmw_zenoh.resolve(name, self.section.namespace, self.node_name)


def _log_unknown(names: list[str]) -> None:
    """A command's names that no joint has, each once (``Commands.newly_unknown``)."""
    for name in names:
        log.warning("ros2: a command names no joint of this gateway: %r", name)


def _when_all(futures: list[Future], done_message: str) -> Future:
    """A Trigger response once every bus's future is done: success when none failed."""
    answer: Future = Future()
    left = [len(futures)]
    lock = threading.Lock()

    def one_done(_: Future) -> None:
        with lock:
            left[0] -= 1
            if left[0]:
                return
        failures = [f.exception() for f in futures if f.exception() is not None]
        if failures:
            reasons = "; ".join(error_reply(e)["error"]["message"] for e in failures if e)
            answer.set_result({"success": False, "message": reasons})
        else:
            answer.set_result({"success": True, "message": done_message})

    if not futures:
        answer.set_result({"success": True, "message": done_message})
    for future in futures:
        future.add_done_callback(one_done)
    return answer


def _number(value: float | None) -> float:
    return math.nan if value is None else float(value)
