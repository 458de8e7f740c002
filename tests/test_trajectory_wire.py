"""Trajectories played on real buses, checked on the wire: a gateway on simulators (three
Inspire LA actuators on one 921600-baud pty, two DS servos on another, a ZLAC706 on python-can's
virtual bus: ``tests.simulated_buses``) driven through ``GatewayApi`` and ``Trajectories``, whose
loop part (``tick``) is called every round as the bridge's ``publish_forever`` calls it.

What the simulators received is the evidence: each tick frame decoded (every LA actuator of a
bus in one 0xF3 frame, the DS servos in one SYNC WRITE), with the host-side time it reached
the device. A tick's slot is recovered from its values: the latest slot since the previous
tick's, at or before the frame arrived, whose values it carries (a tick goes out at its slot,
or late and then the next is a full period after it, so slots may be missed, never repeated).
The interpolant at each slot is the pure ``gateway.trajectory.interpolation`` (tested on its
own) from each device's state before the play.

No tick may reach a device before its slot; how late one may be is left to
``bench_trajectory``, which measures lateness against the 1 ms the contract names (the
simulators share the process, and this machine's two cores, with the gateway). "Nothing was
sent" is checked after the start it would have had, and a later exchange on the bus answered;
"nothing more was sent" counts the frames after the end, not the milliseconds."""

from __future__ import annotations

import itertools
import json
import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from functools import partial

import pytest
import zenoh

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs import zlac706_common as zcommon
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.ros2.face import PLAY_JSON_MAX
from busgate.gateway.scheduler.plays import RAMP_S
from busgate.gateway.scheduler.trajectory_ticks import GRID_STRETCH, ON_TIME_S
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.ds_servo import DsServoDevice
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.trajectory.interpolation import INTERPOLATIONS, Path, paths_of, sent
from busgate.gateway.trajectory.lanes import answer
from busgate.gateway.trajectory.playing import Trajectories
from busgate.schemas.config import SerialBus
from busgate.schemas.events import EVENT_ADAPTER
from busgate.schemas.trajectory import MAX_TRAJECTORY_PAYLOAD, TrajectoryPlay
from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port, wait_until
from tests.gateway_process import GatewayProcess, bus_table, write_config
from tests.simulated_buses import SimulatedGateway, simulated_gateway
from tests.test_zenoh_api import connected, get
from tests.wire_frames import no_base, received, tick_targets, written, written_speed

BASE = "busgate/gw"
#: Reply margins that leave room, between the ticks of a 20 ms period, for the polls that
#: measure where the devices are (tests.simulated_buses).
MARGIN_MS = 10
PERIOD = 0.02  # every device's follow period (the default)
GRID = PERIOD * GRID_STRETCH  # the slots' spacing (rule 1 of trajectory_ticks.py)
#: Ticks a bus may still send once a play has ended: the one its thread was sending then.
IN_FLIGHT = 1
ROUND_S = 0.005  # the bridge's publish round (PUBLISH_EVERY_S)
DRIFT_S = 0.05  # how far behind its grid a feedback may come: half of FEEDBACK_EVERY_S
ROUNDING_S = 1e-5  # the float rounding of a grid of Unix times summed 0.1 s at a time
LA_IDS = {"la1": 1, "la2": 2, "la3": 3}
DS_IDS = {"arm1": 1, "arm2": 2}
EVERY_SERVO = [*LA_IDS, *DS_IDS]

_ids = itertools.count()


@pytest.fixture(scope="module")
def world() -> Iterator[SimulatedGateway]:
    with simulated_gateway(margin_ms=MARGIN_MS) as world:
        yield world


@dataclass
class Tick:
    """A tick frame as a device received it: when (bus clock) and each target, by id."""

    start: float
    values: dict[int, int]


@dataclass
class Played:
    """A play accepted: its command, its start on both clocks, each device's path."""

    id: str
    command: dict
    reply: dict
    start_at: float
    start_bus: float
    paths: dict[str, Path]
    marks: dict[str, int]  # each simulator's received frames before the play

    def restarted(self, starts: dict[str, float]) -> Played:
        """The same play had these devices started from ``starts``."""
        values = [starts.get(name, self.paths[name].knots[0].value) for name in self.paths]
        paths = paths_of(TrajectoryPlay.model_validate(self.command), values)
        return replace(self, paths=dict(zip(self.paths, paths, strict=True)))

    def expected(self, ids: dict[str, int]) -> Callable[[int], dict[int, int]]:
        """Slot k's targets of the devices ``ids`` names, by id."""
        return lambda k: {i: sent(self.paths[name].at(k * GRID)) for name, i in ids.items()
                          if name in self.paths}


class Player:
    """The trajectory key of the world's gateway: what it published (feedback and results)
    and its events are kept; ``run_until`` calls ``tick`` each round, as the bridge does."""

    def __init__(self, world: SimulatedGateway) -> None:
        self.world = world
        self.published: list[tuple[str, dict]] = []
        self.events: list[DeviceEvent] = []
        self.trajectories = Trajectories(world.api, BASE, self._publish, self.events.append,
                                         no_base)

    def _publish(self, key: str, body: dict) -> None:
        self.published.append((key, body | {"_at": now()}))

    def ask(self, command: dict) -> dict:
        """The reply the trajectory key gives (the bridge's own path, refusals mapped)."""
        return answer(self.trajectories.command, json.dumps(command).encode())

    def play(self, devices: list[str], points: list[dict], *, lead_s: float = 0.12,
             **fields) -> Played:
        """Play ``points`` on ``devices`` from ``lead_s`` ahead; accepted, or the test fails."""
        starts = start_values(self.world, devices, "rpms" in points[0])
        marks = marks_of(self.world)
        start_at = time.time() + lead_s
        command = {"op": "play", "id": f"t{next(_ids)}", "devices": devices, "points": points,
                   "start_at": start_at, **fields}
        reply = self.ask(command)
        start_bus = now() + (start_at - time.time())
        assert reply["ok"], reply
        assert reply["trajectory"]["start_at"] == start_at
        paths = paths_of(TrajectoryPlay.model_validate(command), starts)
        return Played(command["id"], command, reply, start_at, start_bus,
                      dict(zip(devices, paths, strict=True)), marks)

    def run_until(self, done: Callable[[], object], timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < deadline, "not done in time"
            self.trajectories.tick()
            time.sleep(ROUND_S)

    def result(self, trajectory: str) -> dict | None:
        results = [body for key, body in self.published
                   if key == f"{BASE}/trajectory/{trajectory}/feedback" and "result" in body]
        assert len(results) <= 1, results
        return results[0] if results else None

    def finished(self, played: Played, timeout: float = 5.0) -> dict:
        self.run_until(lambda: self.result(played.id), timeout)
        return self.result(played.id)

    def feedback(self, trajectory: str) -> list[dict]:
        return [body for key, body in self.published
                if key == f"{BASE}/trajectory/{trajectory}/feedback" and "result" not in body]

    def ended(self, trajectory: str) -> list[dict]:
        """Its ``trajectory_ended`` events, each checked to carry the final errors of its
        result (taken out: the result shows them)."""
        found = []
        for event in self.events:
            if event.type == "trajectory_ended" and event.fields["id"] == trajectory:
                EVENT_ADAPTER.validate_python(
                    {"ts": 0.0, "device": event.device, "type": event.type, **event.fields})
                fields = dict(event.fields)
                assert fields.pop("errors") == self.result(trajectory)["errors"]
                found.append(fields)
        return found


@pytest.fixture
def player(world) -> Iterator[Player]:
    player = Player(world)
    yield player
    for running in player.ask({"op": "status"})["trajectories"]:  # a test that failed midway
        player.ask({"op": "cancel", "id": running["id"]})


def simulators(world: SimulatedGateway):
    return [("uart0", world.la_sim), ("uart1", world.ds_sim), ("can0", world.can_sim)]


def marks_of(world: SimulatedGateway) -> dict[str, int]:
    """How many frames each simulator has received so far."""
    return {name: len(sim.recorder.received()) for name, sim in simulators(world)}


def start_values(world: SimulatedGateway, devices: list[str], speeds: bool) -> list[float]:
    """Where the API starts each device's path: its state's target (nothing plays it now),
    read once every device has been read since this call (so no poll changes it meanwhile)."""
    mark = time.time()
    wait_until(lambda: all(world.api.devices[d][0].states[d]["ts"] > mark for d in devices))
    fields = ("target_speed_rpm", "speed_rpm") if speeds else ("target", "position")
    values = []
    for device in devices:
        state = world.api.devices[device][0].states[device]
        values.append(next(float(state[f]) for f in fields if state.get(f) is not None))
    return values


def ticks(simulator, since: int, codec=None) -> list[Tick]:
    """The tick frames (follow frames without reply) a serial simulator received after its
    ``since``-th frame."""
    codec = codec or (la if simulator.codec is la else ds)
    return [Tick(record.start, targets) for record, frame in received(simulator, since, codec)
            if (targets := tick_targets(frame)) is not None]


def speed_ticks(world: SimulatedGateway, since: int) -> list[Tick]:
    """The speed writes the ZLAC706 received after its ``since``-th frame (raw values, id 5)."""
    return [Tick(record.start, {5: speed})
            for record, frame in received(world.can_sim, since, zcan)
            if (speed := written_speed(frame)) is not None]


def slots_of(found: list[Tick], start_bus: float,
             expected: Callable[[int], dict[int, int]]) -> list[int]:
    """Each tick's slot (see the module's docstring); fails on a tick that carries the values
    of no slot it could be."""
    slots, previous = [], -1
    for tick in found:
        latest = math.floor((tick.start - start_bus) / GRID + 0.05)
        for k in range(latest, previous, -1):
            if expected(k) == tick.values:
                break
        else:
            raise AssertionError(
                f"the tick at {tick.start - start_bus:+.4f} s carries {tick.values}: no slot "
                f"after {previous} does (slot {latest}: {expected(latest)})")
        slots.append(k)
        previous = k
    return slots


def assert_never_early(found: list[Tick], slots: list[int], start_bus: float, name: str) -> None:
    """No tick reached its device before its slot's time (on the bus's clock, less 0.1 ms of
    the frame's own transmission). How late a tick may be is a matter of this host's load:
    ``bench_trajectory`` measures it against the 1 ms the contract names."""
    for tick, k in zip(found, slots, strict=True):
        assert tick.start >= start_bus + k * GRID - 1e-4, f"{name}: slot {k} early"


def settled(world: SimulatedGateway, device: str) -> None:
    """A later exchange on the device's bus was answered: what was queued has gone out."""
    command(world, device, {"op": "ping"} if device.startswith("arm") else {"op": "status"})


def command(world: SimulatedGateway, device: str, fields: dict) -> dict:
    reply = world.api.command(device, json.dumps(fields).encode()).result(5)
    assert reply["ok"], reply
    return reply


# -- every slot, its interpolant, on every bus together ----------------------------------------

POINTS = {
    "linear": [
        {"t_s": 0.2, "positions": [400, 800, 1200, 1000, 3000]},
        {"t_s": 0.45, "positions": [1200, 300, 1500, 2500, 1500]},
    ],
    "cubic": [
        {"t_s": 0.2, "positions": [400, 800, 1200, 1000, 3000],
         "velocities": [2000, -1000, 500, 3000, -4000]},
        {"t_s": 0.45, "positions": [1200, 300, 1500, 2500, 1500]},
    ],
    "quintic": [
        {"t_s": 0.2, "positions": [400, 800, 1200, 1000, 3000],
         "velocities": [2000, -1000, 500, 3000, -4000],
         "accelerations": [-5000, 8000, 0, 10000, 20000]},
        {"t_s": 0.45, "positions": [1200, 300, 1500, 2500, 1500]},
    ],
}


@pytest.mark.parametrize("interpolation", INTERPOLATIONS)
def test_every_tick_carries_the_interpolant_at_its_slot_on_both_buses_together(
        world, player, interpolation):
    """From where each device is commanded, every tick of both buses carries the interpolant
    at its slot, rounded; each bus's first tick is slot 0, sent at start_at; the two buses
    tick the same slots together; the last point's value goes out before the result
    (``succeeded``)."""
    played = player.play(EVERY_SERVO, POINTS[interpolation], interpolation=interpolation)
    assert player.finished(played)["result"] == "succeeded"
    timed = {}
    for name, simulator, ids in (("uart0", world.la_sim, LA_IDS), ("uart1", world.ds_sim, DS_IDS)):
        found = ticks(simulator, played.marks[name])
        slots = slots_of(found, played.start_bus, played.expected(ids))
        assert slots[0] == 0, name
        assert_never_early(found, slots, played.start_bus, name)
        last = played.expected(ids)(math.ceil(0.45 / GRID))
        assert found[-1].values == last, f"{name}: the last point's values were never sent"
        timed[name] = set(slots)
    assert 0 in timed["uart0"] & timed["uart1"]


def test_a_trajectory_ending_between_slots_sends_its_last_point_before_it_succeeds(
        world, player):
    """The last point at 0.49 s: the slot at 0.50 s carries it; the verdict waits for it."""
    played = player.play(["la1", "arm1"], [{"t_s": 0.49, "positions": [1700, 3500]}])
    assert player.finished(played)["result"] == "succeeded"
    assert ticks(world.la_sim, played.marks["uart0"])[-1].values == {1: 1700}
    assert ticks(world.ds_sim, played.marks["uart1"])[-1].values == {1: 3500}


def test_feedback_comes_ten_times_a_second_then_the_result_there_and_as_an_event(
        world, player):
    """Ten a second: the n-th feedback at the first's time + n × 0.1 s or up to half a period
    after (so a load hiccup passes, while over 15 of them a feedback a round late each time,
    75 ms behind, does not); each with every device's desired, commanded, measured values
    and error."""
    played = player.play(["la2", "arm2"], [{"t_s": 1.5, "positions": [600, 2000]}],
                         client="alice")
    result = player.finished(played)
    feedback = player.feedback(played.id)
    assert result["result"] == "succeeded" and result["id"] == played.id
    assert set(result["errors"]) == {"la2", "arm2"}
    first = feedback[0]["ts"]
    for n, body in enumerate(feedback):  # the grid adds 0.1 s a feedback: at Unix-time
        # magnitudes each sum rounds by up to 0.12 µs, so n of them may land a few ulps early
        on_grid = first + n * 0.1 - ROUNDING_S
        assert on_grid <= body["ts"] < on_grid + DRIFT_S, (n, body["ts"])
    assert feedback[-1]["ts"] >= played.start_at + 1.5 - 0.1  # to the end
    playing = [body for body in feedback if body["t_s"] > 0.05]
    assert playing, feedback
    for body in playing:
        assert body["id"] == played.id and math.isclose(
            body["t_s"], body["ts"] - played.start_at, abs_tol=1e-6)
        for device in body["devices"]:
            path = played.paths[device["device"]]
            assert device["desired"] == sent(path.at(body["t_s"]))
            assert isinstance(device["commanded"], int) and isinstance(device["measured"], int)
        assert [d["device"] for d in body["devices"]] == ["la2", "arm2"]
    assert any(d["error"] is not None for body in playing for d in body["devices"])
    started = [e.fields for e in player.events if e.type == "trajectory_started"]
    assert started == [{"id": played.id, "client": "alice", "start_at": played.start_at,
                        "end_at": played.start_at + 1.5}]
    assert player.ended(played.id) == [{"id": played.id, "client": "alice",
                                        "result": "succeeded"}]
    assert set(player.result(played.id)["errors"]) == {"la2", "arm2"}
    assert all(e.device == "*" for e in player.events)


def test_status_lists_what_plays(world, player):
    played = player.play(["la3"], [{"t_s": 0.3, "positions": [900]}])
    [listed] = player.ask({"op": "status"})["trajectories"]
    assert listed["id"] == played.id and listed["devices"] == ["la3"]
    assert listed["start_at"] == played.start_at and listed["end_at"] == played.start_at + 0.3
    player.finished(played)
    assert player.ask({"op": "status"}) == {"ok": True, "trajectories": []}


# -- the bus's own rules hold through a trajectory ---------------------------------------------


def test_gaps_intervals_commands_and_polls_keep_their_rules_through_a_trajectory(world, player):
    """The UART gap after every exchange; no follow interval short of the period by more than
    ON_TIME_S (trajectory_ticks rule 1); a command during the play is carried out, polls go on
    (precedence), and the ticks keep to their slots all the same."""
    before = {name: world.runners[name].statistics() for name in ("uart0", "uart1")}
    played = player.play(EVERY_SERVO, POINTS["linear"])
    player.run_until(lambda: time.time() > played.start_at + 0.2)
    polled = world.runners["uart0"].states["la1"]["ts"]
    assert command(world, "la1", {"op": "status"})["state"]["device"] == "la1"
    assert player.finished(played)["result"] == "succeeded"
    assert world.runners["uart0"].states["la1"]["ts"] > polled
    slots_of(ticks(world.la_sim, played.marks["uart0"]), played.start_bus,
             played.expected(LA_IDS))
    for name in ("uart0", "uart1"):
        runner, stats = world.runners[name], world.runners[name].statistics()
        assert stats.smallest_gap_s >= runner.timing.gap_s, name
        assert stats.follow_intervals > before[name].follow_intervals
        assert stats.follow_error_min_s >= -ON_TIME_S, name


# -- cancel and replace ------------------------------------------------------------------------


def test_a_canceled_trajectory_holds_every_position_within_a_period(world, player):
    played = player.play(EVERY_SERVO, [{"t_s": 1.0, "positions": [100, 1900, 100, 500, 3500]}])
    player.run_until(lambda: time.time() > played.start_at + 0.3)
    canceled = marks_of(world)
    assert player.ask({"op": "cancel", "id": played.id}) == {"ok": True, "canceled": played.id}
    assert player.result(played.id)["result"] == "canceled"
    assert player.ended(played.id) == [{"id": played.id, "result": "canceled"}]
    settled(world, "la1")
    settled(world, "arm1")
    for name, simulator in (("uart0", world.la_sim), ("uart1", world.ds_sim)):
        assert len(ticks(simulator, canceled[name])) <= IN_FLIGHT, name
    assert player.ask({"op": "cancel", "id": played.id})["error"]["code"] == "bad_command"


def test_a_follow_target_for_a_playing_device_is_refused_busy_and_never_sent(world, player):
    """A follow stream and a trajectory would fight over the device's target: while it
    plays, its follow targets are refused ``busy``; once it is over, one is taken again."""
    played = player.play(["la2"], [{"t_s": 0.6, "positions": [1777]}])
    player.run_until(lambda: time.time() > played.start_at + 0.1)
    refused = world.api.follow("la2", b'{"position": 444}')
    assert refused is not None and refused["error"]["code"] == "busy"
    player.finished(played)
    settled(world, "la2")
    assert all(444 not in t.values.values() for t in ticks(world.la_sim, played.marks["uart0"]))
    assert world.api.follow("la2", b'{"position": 445}') is None  # no trajectory: taken
    assert command(world, "la2", {"op": "end_follow"})["ok"]


def test_a_play_naming_a_playing_device_takes_it_over_and_the_old_one_is_replaced(world, player):
    """The old trajectory's ticks stop carrying the device taken (and the one it leaves
    holds); the new one's carry its path from where the old one had commanded it."""
    old = player.play(["la1", "la2"], [{"t_s": 1.0, "positions": [1800, 1800]}])
    player.run_until(lambda: time.time() > old.start_at + 0.3)
    new = player.play(["la2", "arm1"], [{"t_s": 0.3, "positions": [200, 1000]}], lead_s=0.05)
    assert player.result(old.id)["result"] == "replaced"
    assert player.ended(old.id) == [{"id": old.id, "result": "replaced"}]
    assert player.finished(new)["result"] == "succeeded"
    found = ticks(world.la_sim, old.marks["uart0"])
    before = [t for t in found if t.start < new.start_bus - 1e-4]
    after = [t for t in found if t.start >= new.start_bus - 1e-4]
    slots_of(before, old.start_bus, old.expected({"la1": 1, "la2": 2}))
    # Where the new one starts la2: its last tick when the play was taken in (the last one
    # sent, or the one before when a tick went out while the play was being checked).
    start = after[0].values[2]
    assert start in [t.values[2] for t in before[-2:]]
    new = new.restarted({"la2": start})
    slots = slots_of(after, new.start_bus, new.expected({"la2": 2}))  # la1 holds: not sent
    assert slots[0] == 0
    assert_never_early(after, slots, new.start_bus, "uart0")
    slots_of(ticks(world.ds_sim, new.marks["uart1"]), new.start_bus, new.expected({"arm1": 1}))


def test_a_trajectory_played_right_after_another_starts_where_that_one_left(world, player):
    """No state read since the first one's last tick: the second starts from that tick's
    values, not from a target read before it."""
    first = player.play(["la3", "arm2"], [{"t_s": 0.3, "positions": [1500, 3900]}])
    player.finished(first)
    second = player.ask({"op": "play", "id": "right-after", "devices": ["la3", "arm2"],
                         "start_at": time.time() + 0.05,
                         "points": [{"t_s": 0.3, "positions": [500, 100]}]})
    assert second["ok"], second
    player.run_until(lambda: player.result("right-after"))
    for simulator, mark, device in ((world.la_sim, first.marks["uart0"], 3),
                                    (world.ds_sim, first.marks["uart1"], 2)):
        found = ticks(simulator, mark)
        start = second["trajectory"]["start_at"]
        start_bus = now() + (start - time.time())
        last_of_first = [t for t in found if t.start < start_bus - 1e-4][-1]
        first_of_second = next(t for t in found if t.start >= start_bus - 1e-4)
        assert first_of_second.values == last_of_first.values == {
            device: [1500, 3900][device == 2]}


def test_a_play_right_after_an_actuators_follow_stream_starts_where_its_last_tick_left(
    world, player
):
    """An LA's follow frame has no reply, and no poll fits between a bus's follow ticks (the
    world's margin; la1 streams all along): its state says the target it had before the
    stream. A play checked then starts from the stream's last tick (``plays`` rule 4), not
    from that older target, which its first tick would jump back to (an audit: 1560, then
    1160)."""
    runner = world.api.devices["la3"][0]
    before = start_values(world, ["la3"], speeds=False)[0]
    target = 1800 if before < 1000 else 200
    mark = len(world.la_sim.recorder.received())

    def streaming(la3: bool = False) -> bool:
        for device in ("la1", "la3") if la3 else ("la1",):
            payload = {"position": target if device == "la3" else 1000}
            assert world.api.follow(device, json.dumps(payload).encode()) is None
        time.sleep(0.01)
        return True

    for _ in range(5):
        streaming(la3=True)
    command(world, "la3", {"op": "end_follow"})
    wait_until(lambda: streaming() and not runner.streams.following("la3"))
    reply = player.ask({"op": "play", "id": "after-a-stream", "devices": ["la3"],
                        "start_at": time.time() + 0.05,
                        "points": [{"t_s": 0.2, "positions": [1000]}]})
    assert reply["ok"], reply
    player.run_until(lambda: player.result("after-a-stream"))
    start_bus = now() + (reply["trajectory"]["start_at"] - time.time())
    found = [t for t in ticks(world.la_sim, mark) if 3 in t.values]
    last_of_stream = [t for t in found if t.start < start_bus - 1e-4][-1]
    first_of_play = next(t for t in found if t.start >= start_bus - 1e-4)
    assert last_of_stream.values[3] == target
    assert first_of_play.values == {3: target}, f"the state's target was {before}"


# -- speeds ------------------------------------------------------------------------------------


def test_a_speed_trajectory_sends_each_slots_rpm_and_a_cancel_ramps_it_to_zero(world, player):
    """Each tick the path's speed at its slot; canceled, the speed ramps from the last one
    sent to 0 over RAMP_S on the same grid, then the stale-stream stop writes 0 rpm."""
    command(world, "wheel", {"op": "set_mode", "mode": "velocity"})
    command(world, "wheel", {"op": "enable"})
    try:
        played = player.play(["wheel"], [{"t_s": 0.3, "rpms": [300.0]},
                                         {"t_s": 2.0, "rpms": [300.0]}])
        player.run_until(lambda: time.time() > played.start_at + 0.5)
        canceled_at = now()
        player.ask({"op": "cancel", "id": played.id})
        assert player.result(played.id)["result"] == "canceled"

        def stopped() -> bool:  # the ramp's last tick (0 rpm), then the stale-stream stop
            last_two = speed_ticks(world, played.marks["can0"])[-2:]
            return all(t.values == {5: 0} and t.start > canceled_at for t in last_two)

        wait_until(stopped)
        found = speed_ticks(world, played.marks["can0"])
        path, full = played.paths["wheel"], zcommon.speed_raw_truncated(300.0)
        last_full = max(i for i, t in enumerate(found) if t.values == {5: full})
        slots = slots_of(found[: last_full + 1], played.start_bus,
                         lambda k: {5: zcommon.speed_raw_truncated(path.at(k * GRID))})
        ramp_from = slots[-1]

        def ramp(k: int) -> dict[int, int]:
            left = max(0.0, 1 - (k - ramp_from) * GRID / RAMP_S)
            return {5: zcommon.speed_raw_truncated(300.0 * left)}

        *ramped, stop = found[last_full + 1:]
        ramp_slots = slots_of(ramped, played.start_bus, ramp)
        assert ramped[0].values[5] < full and ramped[-1].values == stop.values == {5: 0}
        assert ramp_slots[-1] >= ramp_from + math.ceil(RAMP_S / GRID)  # 0 reached at RAMP_S
    finally:
        command(world, "wheel", {"op": "velocity", "rpm": 0})
        command(world, "wheel", {"op": "disable"})


def test_a_wheel_in_absolute_position_mode_plays_positions_slot_by_slot(world, player):
    """A ZLAC706 on CAN in absolute position mode plays positions: each tick writes the
    path's position at its slot to the target register (16), from the wheel's position,
    and no speed."""
    for fields in ({"op": "set_mode", "mode": "position"},
                   {"op": "set_position_mode", "relative": False}, {"op": "enable"}):
        command(world, "wheel", fields)
    try:
        played = player.play(["wheel"], [{"t_s": 0.2, "positions": [3000]},
                                         {"t_s": 0.4, "positions": [-1000]}])
        assert player.finished(played)["result"] == "succeeded"
        wait_until(lambda: player.ask({"op": "status"})["trajectories"] == [])
        found = [Tick(record.start, {5: value})
                 for record, frame in received(world.can_sim, played.marks["can0"], zcan)
                 if (value := written(frame, zcan.CanRegister.TARGET_POSITION)) is not None]
        path = played.paths["wheel"]
        slots = slots_of(found, played.start_bus, lambda k: {5: sent(path.at(k * GRID))})
        assert slots[0] == 0 and found[-1].values == {5: -1000}
        assert len(found) >= 0.4 / GRID - 1  # a tick a slot, or nearly (a late one skips)
        assert_never_early(found, slots, played.start_bus, "wheel")
        assert speed_ticks(world, played.marks["can0"]) == []
    finally:
        command(world, "wheel", {"op": "disable"})
        command(world, "wheel", {"op": "set_mode", "mode": "velocity"})


# -- aborts ------------------------------------------------------------------------------------


def enabled_again(world: SimulatedGateway) -> None:
    """After a gateway e-stop: every device's re-enable op (the wheel left disabled)."""
    for device in LA_IDS:
        command(world, device, {"op": "enable"})
    for device in DS_IDS:
        command(world, device, {"op": "torque", "on": True})
    command(world, "wheel", {"op": "enable"})
    command(world, "wheel", {"op": "disable"})


TICK_FRAMES = ("GroupFollowCommand", "FollowCommand", "SyncWrite")


def stop_wires(driver_class, ids: dict[str, int]) -> set[str]:
    """Each device's e-stop frame (an LA's ESTOP control, a DS servo's torque off), as a
    fresh driver of its kind sends it."""
    return {driver_class(name, ident, follow_period_s=PERIOD).safe_stop()[-1].wire.hex()
            for name, ident in ids.items()}


def frames_to_stop(simulator, since: int, moment: float, stops: set[str]) -> tuple[list, object]:
    """What ``simulator`` received after its ``since``-th frame that reached it after
    ``moment`` and is no tick, up to its first e-stop frame: (the frames before it, it)."""
    before = []
    for record in simulator.recorder.received()[since:]:
        if record.start <= moment or record.frame in TICK_FRAMES:
            continue
        if record.wire in stops:
            return before, record
        before.append(record)
    raise AssertionError(f"no e-stop frame after {moment}: {before}")


def test_an_estop_aborts_the_trajectory_and_no_tick_follows_its_frames(world, player):
    played = player.play(EVERY_SERVO, [{"t_s": 1.0, "positions": [1000, 1000, 1000, 2048,
                                                                  2048]}])
    player.run_until(lambda: time.time() > played.start_at + 0.2)
    called = now()
    try:
        stops = world.api.stop_every_bus()
        player.run_until(lambda: all(stop.done() for stop in stops))
        result = player.finished(played)
        assert (result["result"], result["reason"]) == ("aborted", "estop")
        assert player.ended(played.id) == [{"id": played.id, "result": "aborted",
                                            "reason": "estop"}]
        for name, simulator, wires in (
                ("uart0", world.la_sim, stop_wires(InspireLaDriver, LA_IDS)),
                ("uart1", world.ds_sim, stop_wires(DsServoDriver, DS_IDS))):
            before, stop = frames_to_stop(simulator, played.marks[name], called, wires)
            # ahead of everything: at most the exchange already under way when it was asked
            assert len(before) <= 1, before
            late = [t for t in ticks(simulator, played.marks[name]) if t.start > stop.start]
            assert late == [], name
    finally:
        enabled_again(world)


def test_a_play_that_came_before_an_estop_never_starts_after_its_reset(world, player):
    """A play waits in its lane (its parse: a tenth of a second for a large one) while an
    e-stop and its reset come: it played after the reset, and la1 moved. It is refused
    ``estopped``, nothing ticks; one that came after the reset plays."""
    came_under = world.api.estops
    stops = world.api.stop_every_bus()
    player.run_until(lambda: all(stop.done() for stop in stops))
    enabled_again(world)
    marks = marks_of(world)
    late = json.dumps({"op": "play", "id": "late", "devices": ["la1"],
                       "points": [{"t_s": 0.2, "positions": [700]}]}).encode()
    reply = answer(lambda payload: player.trajectories.command(payload, came_under), late)
    assert reply["error"]["code"] == "estopped", reply
    time.sleep(0.3)
    assert ticks(world.la_sim, marks["uart0"]) == []
    played = player.play(["la1"], [{"t_s": 0.2, "positions": [700]}])
    assert player.finished(played)["result"] == "succeeded"


def test_a_play_over_the_keys_megabyte_is_taken_where_its_sender_allows_it(world, player):
    """The ROS 2 face's plays are its own JSON of a message of at most 1 MiB of CDR, some
    three times the bytes: a message of 9,000 points of two joints, within both of its
    limits, was refused at the trajectory key's megabyte. The key's own limit stays."""
    tiny = 1.234567891e-09
    points = [{"t_s": 2.0 + 0.02 * k + 1e-9, "positions": [1000, 2048],
               "velocities": [tiny, tiny], "accelerations": [tiny, tiny]} for k in range(9000)]
    payload = json.dumps({"op": "play", "id": "big", "devices": ["la1", "arm1"],
                          "points": points}).encode()
    assert MAX_TRAJECTORY_PAYLOAD < len(payload) < PLAY_JSON_MAX
    assert answer(player.trajectories.command, payload)["error"]["code"] == "too_large"
    try:
        taken = answer(partial(player.trajectories.command, limit=PLAY_JSON_MAX), payload)
        assert taken["ok"], taken
    finally:
        player.ask({"op": "cancel", "id": "big"})


def test_an_estop_before_the_start_aborts_it_at_once_and_nothing_ticks(world, player):
    played = player.play(["la1", "arm1"], [{"t_s": 0.3, "positions": [100, 100]}], lead_s=0.5)
    try:
        stops = world.api.stop_every_bus()
        player.run_until(lambda: all(stop.done() for stop in stops))
        player.run_until(lambda: player.result(played.id))
        result = player.result(played.id)
        assert (result["result"], result["reason"]) == ("aborted", "estop")
        assert result["_at"] < played.start_bus
    finally:
        enabled_again(world)
    player.run_until(lambda: now() > played.start_bus + 3 * PERIOD)
    for name, simulator in (("uart0", world.la_sim), ("uart1", world.ds_sim)):
        assert ticks(simulator, played.marks[name]) == [], name


def test_an_estop_the_watcher_missed_still_aborts_the_trajectory(world, player):
    """E-stopped and enabled again between two rounds of the loop: the bus took the devices
    out of their trajectory, which is over, and told as the e-stop it was (the refusal says
    so, whatever the drivers' state says by then)."""
    played = player.play(["la1", "la2"], [{"t_s": 1.0, "positions": [300, 300]}])
    player.run_until(lambda: time.time() > played.start_at + 0.2)
    for stop in world.api.stop_every_bus():  # no round of the loop meanwhile
        stop.result(5)
    enabled_again(world)
    result = player.finished(played)
    assert (result["result"], result["reason"]) == ("aborted", "estop")


def test_a_device_going_offline_aborts_the_trajectory(world, player, wait_for):
    played = player.play(["la1", "la2", "arm1"], [{"t_s": 1.5, "positions": [1900, 1900, 4000]}])
    player.run_until(lambda: time.time() > played.start_at + 0.1)
    world.la_sim.faults.configure(silent_ids=frozenset({2}))
    try:
        result = player.finished(played)
        assert (result["result"], result["reason"]) == ("aborted", "la2 offline")
    finally:
        world.la_sim.faults.configure(silent_ids=frozenset())
        wait_for(lambda: world.api.devices["la2"][1].online)


def test_the_clients_departure_aborts_its_trajectory_and_only_its(world, player):
    alices = player.play(["la1"], [{"t_s": 1.0, "positions": [500]}], client="alice")
    bobs = player.play(["la3"], [{"t_s": 0.6, "positions": [500]}], client="bob")
    player.run_until(lambda: time.time() > alices.start_at + 0.1)
    player.trajectories.client_left("alice")
    result = player.result(alices.id)
    assert (result["result"], result["reason"]) == ("aborted", "client gone")
    assert player.ended(alices.id) == [{"id": alices.id, "client": "alice", "result": "aborted",
                                        "reason": "client gone"}]
    assert player.finished(bobs)["result"] == "succeeded"


def test_a_claim_that_lapses_aborts_the_trajectory_played_under_it(world, player):
    command(world, "la1", {"op": "claim", "client": "alice", "ttl_s": 0.3})
    played = player.play(["la1"], [{"t_s": 1.0, "positions": [1500]}], client="alice")
    result = player.finished(played)
    assert (result["result"], result["reason"]) == ("aborted", "claim on la1 lost")
    assert result["_at"] - played.start_bus < 1.0


def test_another_client_claiming_a_device_aborts_the_trajectory_moving_it(world, player):
    played = player.play(["la2"], [{"t_s": 1.0, "positions": [200]}])
    player.run_until(lambda: time.time() > played.start_at + 0.1)
    command(world, "la2", {"op": "claim", "client": "bob"})
    try:
        result = player.finished(played)
        assert result["result"] == "aborted"
        assert result["reason"].startswith("la2 is claimed by 'bob' (its claim lapses in ")
        aborted = marks_of(world)
        settled(world, "la2")
        assert len(ticks(world.la_sim, aborted["uart0"])) <= IN_FLIGHT
    finally:
        command(world, "la2", {"op": "release", "client": "bob"})


def test_a_device_off_its_path_aborts_the_trajectory(world, player):
    played = player.play(["la3", "arm2"], [{"t_s": 1.0, "positions": [1800, 500]}],
                         path_tolerance=[0, 0])
    result = player.finished(played)
    assert (result["result"], result["reason"]) == ("aborted", "path_tolerance")
    assert any(error not in (None, 0) for error in result["errors"].values())


def test_a_goal_not_reached_in_goal_time_aborts_the_trajectory(world, player):
    """1500 units in 0.1 s, for an actuator whose full stroke (2000) takes a second."""
    target = 1900 if start_values(world, ["la1"], False)[0] < 1000 else 100
    played = player.play(["la1"], [{"t_s": 0.1, "positions": [target]}], goal_tolerance=[1],
                         goal_time_s=0.1)
    result = player.finished(played)
    assert (result["result"], result["reason"]) == ("aborted", "goal_tolerance")
    assert abs(result["errors"]["la1"]) > 1
    assert result["_at"] >= played.start_bus + 0.2


def test_a_device_that_can_no_longer_take_its_target_aborts_the_trajectory_not_the_bus(
        world, player):
    """The wheel switched to position mode while it plays speeds: its ticks are refused by
    its driver. The trajectory is aborted with the reason; the bus goes on (a tick that raised
    would have made the bus thread reopen it)."""
    command(world, "wheel", {"op": "set_mode", "mode": "velocity"})
    command(world, "wheel", {"op": "enable"})
    reconnects = world.runners["can0"].statistics().reconnects
    played = player.play(["wheel"], [{"t_s": 1.0, "rpms": [100.0]}])
    player.run_until(lambda: time.time() > played.start_at + 0.2)
    command(world, "wheel", {"op": "disable"})
    command(world, "wheel", {"op": "set_mode", "mode": "position"})
    result = player.finished(played)
    assert result["result"] == "aborted"
    assert result["reason"].startswith("wheel could not take its target: ")
    assert "velocity mode" in result["reason"]
    assert world.runners["can0"].statistics().reconnects == reconnects
    assert world.api.devices["wheel"][1].online


# -- refusals ----------------------------------------------------------------------------------


def claimed_by_bob(world):
    command(world, "la2", {"op": "claim", "client": "bob"})
    yield
    command(world, "la2", {"op": "release", "client": "bob"})


def estopped_la3(world):
    command(world, "la3", {"op": "estop"})
    yield
    command(world, "la3", {"op": "enable"})


def silent_la3(world):
    world.la_sim.faults.configure(silent_ids=frozenset({3}))
    wait_until(lambda: not world.api.devices["la3"][1].online)
    yield
    world.la_sim.faults.configure(silent_ids=frozenset())
    wait_until(lambda: world.api.devices["la3"][1].online)


ONE_POINT = [{"t_s": 0.2, "positions": [1000, 1000]}]
REFUSALS = {
    "a value out of range": ({"points": [{"t_s": 0.2, "positions": [2001, 1000]}]},
                             None, "out_of_range"),
    "an overshoot between points": ({"points": [
        {"t_s": 0.2, "positions": [1990, 1000], "velocities": [8000, 0]},
        {"t_s": 0.4, "positions": [1990, 1000]}]}, None, "out_of_range"),
    "a device claimed by another": ({"client": "alice"}, claimed_by_bob, "claimed"),
    "require_claim without the claim": ({"client": "alice", "require_claim": True}, None,
                                        "not_claimed"),
    "a device e-stopped": ({"devices": ["la3", "arm1"]}, estopped_la3, "estopped"),
    "a device offline": ({"devices": ["la3", "arm1"]}, silent_la3, "device_timeout"),
    "a device of another gateway": ({"devices": ["la1", "ghost"]}, None, "unknown_device"),
    "positions for a speed device": ({"devices": ["la1", "wheel"]}, None, "bad_command"),
    "points out of order": ({"points": [{"t_s": 0.3, "positions": [1, 1]},
                                        {"t_s": 0.2, "positions": [2, 2]}]},
                            None, "bad_command"),
    "a point short of a device": ({"points": [{"t_s": 0.2, "positions": [1]}]}, None,
                                  "bad_command"),
    "too many points": ({"points": [{"t_s": 0.001 * i, "positions": [1, 1]}
                                    for i in range(1, 10_002)]}, None, "out_of_range"),
    "start_at past": ({"start_at": "past"}, None, "out_of_range"),
    # Numbers the JSON takes, each answered with a refusal code (they were ``internal``).
    "a velocity of 1e308": ({"points": [
        {"t_s": 0.2, "positions": [1000, 1000], "velocities": [1e308, 0]}]},
        None, "out_of_range"),
    "an acceleration of 1e308 in a quintic": ({"interpolation": "quintic", "points": [
        {"t_s": 0.2, "positions": [1000, 1000], "accelerations": [1e308, 0]}]},
        None, "out_of_range"),
    "a position of 10**400": ({"points": [{"t_s": 0.2, "positions": [10**400, 1000]}]},
                              None, "not_json"),  # past a double, as 1e400
    "a velocity the schema takes whose path overshoots": ({"points": [
        {"t_s": 0.2, "positions": [1000, 1000], "velocities": [-1e9, 0]}]},
        None, "out_of_range"),
    "an overshoot between the ticks of an hour-long segment": ({"points": [
        {"t_s": 3600.0, "positions": [1990, 1000], "velocities": [100, 0]}]},
        None, "out_of_range"),
}


@pytest.mark.parametrize("case", REFUSALS)
def test_a_refused_play_has_its_code_and_nothing_reaches_the_wire(world, player, case):
    fields, setup, code = REFUSALS[case]
    steps = setup(world) if setup is not None else iter([None, None])
    next(steps)
    try:
        marks = marks_of(world)
        start_at = time.time() + 0.05
        play = {"op": "play", "id": "refused", "devices": ["la2", "arm1"], "points": ONE_POINT,
                "start_at": start_at} | fields
        if play["start_at"] == "past":
            play["start_at"] = time.time() - 0.001
        reply = player.ask(play)
        assert not reply["ok"] and reply["error"]["code"] == code, reply
        if case == "start_at past":  # the sign says which side of now it is
            assert re.search(r"is -\d+\.\d{3} s from now", reply["error"]["message"]), reply
        assert player.ask({"op": "status"})["trajectories"] == []
        player.run_until(lambda: time.time() > start_at + 3 * PERIOD)
        settled(world, "la1")
        settled(world, "arm2")
        for name, simulator in simulators(world)[:2]:
            assert ticks(simulator, marks[name]) == [], name
        assert speed_ticks(world, marks["can0"]) == []
        assert player.published == [] and player.events == []
    finally:
        next(steps, None)


def test_a_running_trajectorys_id_is_refused_to_another_client_and_replaces_for_its_own(
        world, player):
    """Client B plays an unrelated device under A's running id: refused, naming the id, and
    A's trajectory goes on; A reusing its own id replaces it, as ever."""
    alices = player.play(["la1"], [{"t_s": 1.0, "positions": [700]}], client="alice")
    bobs = {"op": "play", "id": alices.id, "client": "bob", "devices": ["arm1"],
            "points": [{"t_s": 0.2, "positions": [1000]}], "start_at": time.time() + 0.05}
    reply = player.ask(bobs)
    assert reply["error"]["code"] == "bad_command" and repr(alices.id) in reply["error"]["message"]
    assert player.result(alices.id) is None
    assert [t["id"] for t in player.ask({"op": "status"})["trajectories"]] == [alices.id]
    again = alices.command | {"devices": ["arm1"], "points": bobs["points"],
                              "start_at": time.time() + 0.05}
    assert player.ask(again)["ok"]
    assert player.result(alices.id)["result"] == "replaced"


def test_an_hour_long_play_is_checked_by_its_segments_and_plays(world, player):
    """One point an hour away: accepted (on the rule before, every one of its 180,000 ticks
    was sampled and checked first), and cancelled."""
    played = player.play(["la1"], [{"t_s": 3600.0, "positions": [1500]}], goal_time_s=3600.0)
    assert played.reply["trajectory"]["end_at"] == pytest.approx(played.start_at + 3600.0)
    assert player.ask({"op": "cancel", "id": played.id})["ok"]


def test_a_play_needing_more_of_a_bus_than_it_has_is_refused_naming_the_bus():
    """Three actuators at 19200 baud ticking every 10 ms: each 0xF3 frame takes 8 ms of the
    line, its gap 1 ms more, and the bus polls them besides."""
    with SerialSimulator(la, [InspireLaDevice(i) for i in (1, 2, 3)], baudrate=19_200) as sim:
        bus = SerialBus(name="slow", transport="serial", port=sim.port, baudrate=19_200,
                        reply_margin_ms=MARGIN_MS,
                        devices=[{"name": f"la{i}", "kind": "inspire_la", "id": i,
                                  "follow_period_ms": 10} for i in (1, 2, 3)])
        runner = build_bus(bus).start()
        try:
            api = GatewayApi("gw", {"slow": runner})
            wait_until(lambda: all(driver.online for driver in runner.drivers.values()))
            trajectories = Trajectories(api, BASE, lambda key, body: None, lambda event: None,
                                        no_base)
            mark = len(sim.recorder.received())
            start_at = time.time() + 0.05
            reply = answer(trajectories.command, json.dumps({
                "op": "play", "id": "t", "devices": ["la1", "la2", "la3"], "start_at": start_at,
                "points": [{"t_s": 0.2, "positions": [5, 5, 5]}]}).encode())
            assert reply["error"]["code"] == "out_of_range"
            assert "bus slow has no room" in reply["error"]["message"]
            wait_until(lambda: time.time() > start_at + 0.05)
            assert api.command("la1", b'{"op":"status"}').result(5)["ok"]
            assert ticks(sim, mark) == []
        finally:
            runner.stop()


# -- end to end: busgate run, zenoh ------------------------------------------------------------


@dataclass
class Served:
    """``busgate run`` over the LA and DS simulators, and a client session that reaches it."""

    client: zenoh.Session
    la_sim: SerialSimulator
    ds_sim: SerialSimulator

    def subscribe(self, key: str) -> list[dict]:
        received: list[dict] = []
        subscriber = self.client.declare_subscriber(
            key, lambda s: received.append(json.loads(s.payload.to_bytes()) | {"_at": now()}))
        self._subscribers.append(subscriber)
        return received

    def ask(self, command: dict) -> dict:
        [reply] = get(self.client, "busgate/gw1/trajectory", json.dumps(command))
        return reply

    def __post_init__(self) -> None:
        self._subscribers: list = []


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> Iterator[Served]:
    la_sim = SerialSimulator(la, [InspireLaDevice(i) for i in (1, 2, 3)], baudrate=921_600)
    ds_sim = SerialSimulator(ds, [DsServoDevice(1), DsServoDevice(2)], baudrate=1_000_000)
    for simulator in (la_sim, ds_sim):
        simulator.start()
    endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    buses = (bus_table("uart0", la_sim.port, 921_600,
                       {name: ("inspire_la", i) for name, i in LA_IDS.items()},
                       reply_margin_ms=MARGIN_MS),
             bus_table("uart1", ds_sim.port, 1_000_000,
                       {name: ("ds_servo", i) for name, i in DS_IDS.items()},
                       reply_margin_ms=MARGIN_MS))
    # One process: the wire's timing of one gateway (across workers: test_workers.py).
    gateway = GatewayProcess(write_config(tmp_path_factory.mktemp("gw") / "gw.toml", endpoint,
                                          *buses, workers=1))
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    try:
        gateway.wait_for("serving")
        connected(client)

        def online() -> bool:
            [info] = get(client, "busgate/gw1/info", "")
            states = [d["state"] for bus in info["buses"] for d in bus["devices"]]
            return all(state and state["online"] for state in states)

        wait_until(online, timeout=20)
        yield Served(client, la_sim, ds_sim)
    finally:
        client.close()
        assert gateway.stop() == 0
        for simulator in (la_sim, ds_sim):
            simulator.stop()


def test_through_zenoh_a_play_ticks_both_buses_and_reports_on_its_keys(served):
    """The reply names the trajectory's times and devices; both buses tick every slot's
    interpolant from start_at; feedback at least ten a second on the trajectory's feedback
    key, then its result there and on the gateway's events."""
    feedback = served.subscribe("busgate/gw1/trajectory/e2e/feedback")
    events = served.subscribe("busgate/gw1/events")
    marks = {"uart0": len(served.la_sim.recorder.received()),
             "uart1": len(served.ds_sim.recorder.received())}
    start_at = time.time() + 0.3
    command_ = {"op": "play", "id": "e2e", "devices": EVERY_SERVO, "start_at": start_at,
                "interpolation": "cubic",
                "points": [{"t_s": 0.0, "positions": [500, 500, 500, 2048, 2048]},
                           *POINTS["cubic"]]}
    reply = served.ask(command_)
    start_bus = now() + (start_at - time.time())
    assert reply == {"ok": True, "trajectory": {"id": "e2e", "start_at": start_at,
                                                "end_at": start_at + 0.45,
                                                "devices": EVERY_SERVO}}
    wait_until(lambda: any("result" in body for body in feedback))
    *progress, result = feedback
    assert result["result"] == "succeeded" and result["id"] == "e2e"
    first = progress[0]["ts"]
    for n, body in enumerate(progress):
        assert first + n * 0.1 <= body["ts"] < first + n * 0.1 + DRIFT_S, (n, body["ts"])
    assert progress[-1]["t_s"] > 0.35 and len(progress[-1]["devices"]) == 5
    paths = dict(zip(EVERY_SERVO, paths_of(TrajectoryPlay.model_validate(command_),
                                           [0.0] * 5), strict=True))  # from its t_s 0 point
    played = Played("e2e", command_, reply, start_at, start_bus, paths, marks)
    timed = {}
    for name, simulator, ids in (("uart0", served.la_sim, LA_IDS),
                                 ("uart1", served.ds_sim, DS_IDS)):
        found = ticks(simulator, marks[name])
        slots = slots_of(found, start_bus, played.expected(ids))
        assert slots[0] == 0
        assert_never_early(found, slots, start_bus, name)
        timed[name] = set(slots)
    assert 0 in timed["uart0"] & timed["uart1"]
    wait_until(lambda: any(e["type"] == "trajectory_ended" for e in events))
    mine = [(e["type"], e.get("result")) for e in events if e.get("id") == "e2e"]
    assert mine == [("trajectory_started", None), ("trajectory_ended", "succeeded")]
    assert all(e["device"] == "*" for e in events if e.get("id") == "e2e")


def test_through_zenoh_status_cancel_and_a_refusal(served):
    feedback = served.subscribe("busgate/gw1/trajectory/long/feedback")
    reply = served.ask({"op": "play", "id": "long", "devices": ["la1", "arm1"],
                        "points": [{"t_s": 2.0, "positions": [1500, 3000]}]})
    assert reply["ok"] and reply["trajectory"]["start_at"] > time.time()  # start_at: LEAD_S
    [listed] = served.ask({"op": "status"})["trajectories"]
    assert listed["id"] == "long" and listed["devices"] == ["la1", "arm1"]
    refused = served.ask({"op": "play", "id": "bad", "devices": ["la9"],
                          "points": [{"t_s": 1.0, "positions": [1]}]})
    assert refused["error"]["code"] == "unknown_device"
    assert served.ask({"op": "cancel", "id": "long"}) == {"ok": True, "canceled": "long"}
    wait_until(lambda: any("result" in body for body in feedback))
    assert feedback[-1]["result"] == "canceled"
    assert served.ask({"op": "status"}) == {"ok": True, "trajectories": []}


def test_through_zenoh_the_clients_liveliness_token_gone_aborts_its_trajectory(served):
    """alice holds la2's claim and plays it; her token goes: the trajectory is aborted
    ``client gone`` (and her claim released)."""
    feedback = served.subscribe("busgate/gw1/trajectory/alices/feedback")
    token = served.client.liveliness().declare_token("busgate/clients/alice")
    [claimed] = get(served.client, "busgate/gw1/dev/la2/cmd",
                    '{"op":"claim","client":"alice"}')
    assert claimed["ok"]
    reply = served.ask({"op": "play", "id": "alices", "client": "alice", "devices": ["la2"],
                        "points": [{"t_s": 2.0, "positions": [100]}], "require_claim": True})
    assert reply["ok"], reply
    wait_until(lambda: feedback and feedback[-1]["t_s"] > 0.2)
    token.undeclare()
    wait_until(lambda: any("result" in body for body in feedback))
    assert (feedback[-1]["result"], feedback[-1]["reason"]) == ("aborted", "client gone")
