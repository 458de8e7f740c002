"""A base over a bus never started, by plain calls: what ``test_base.py``'s one running base
(built once for the module) does not single out. The base's geometry and joints come from its
config, its callbacks are the ones given, a refused twist says why, the deadman stops only the
driving client's base, a base stopped by a wheel names why, and twists numbered before a stop
are the only ones dropped."""

from __future__ import annotations

import json
import math
from concurrent.futures import Future

import pytest

from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.base.bases import (
    STOPS_KEPT,
    Bases,
    _at,
    _note_stop,
    _sent_before_stop,
)
from busgate.gateway.base.kinematics import Twist
from busgate.gateway.bus.clock import now
from busgate.gateway.service.assembly import build_bus
from tests.test_base import BASE, LEFT, NoTrajectories, config_of
from tests.test_driver_zlac706 import plan
from tests.test_driver_zlac706 import run as applied

#: The left wheel slower than the right: a twist of both limits needs 16.97 rad/s of the
#: right wheel, which the left one (the slower of the two) caps at 13.
SLOW_LEFT = LEFT | {"max_velocity": 13.0}
RADIUS, TRACK = BASE["wheel_radius_m"], BASE["track_m"]


class Recorded:
    """A gateway (``bases.Gateway``) whose devices are the API's, and whose device commands
    are kept, each answered by ``answer`` (device, its fields) at once."""

    def __init__(self, api: GatewayApi) -> None:
        self.name, self.devices = api.name, api.devices
        self.sent: list[tuple[str, dict]] = []
        self.answer = lambda device, fields: {"ok": True}

    def command(self, device: str, payload: bytes) -> Future:
        fields = json.loads(payload)
        self.sent.append((device, fields))
        reply: Future = Future()
        reply.set_result(self.answer(device, fields))
        return reply


class IdleBase:
    """``Bases`` over the API of a bus built and never started: what it hands the bus waits
    in the bus's inbox, and its wheels are offline until told otherwise. With ``recorded``,
    the base's device commands are kept and answered by ``self.gateway`` instead."""

    def __init__(self, bases: tuple[dict, ...] = (BASE,), *, recorded: bool = False,
                 **wheels: dict) -> None:
        config = config_of(list(bases), **{"wl": SLOW_LEFT} | wheels)
        self.runner = build_bus(config.buses[0])
        self.api = GatewayApi("gw", {"can0": self.runner})
        self.gateway = Recorded(self.api)
        self.events: list = []
        self.odometry: list[tuple[str, dict]] = []
        self.bases = Bases(config.bases, self.gateway if recorded else self.api,
                           self.events.append,
                           lambda name, message: self.odometry.append((name, message)),
                           NoTrajectories(), estop_reset_key="busgate/gw/estop/reset")
        self.base = self.bases.bases["base"]

    def read(self, wheel: str, position: float | None, ts: float | None,
             velocity: float | None = None, **more) -> None:
        """A state of ``wheel``, online in velocity mode unless ``more`` says otherwise."""
        joint = {"position": position, "velocity": velocity}
        state = {"online": True, "mode": "velocity", "ts": ts, "joint": joint}
        self.bases.take_state(wheel, state | more)

    def command(self, fields: dict) -> dict:
        return self.bases.command("base", json.dumps(fields).encode()).result(1)

    def wheels_online(self, *names: str) -> None:
        """The wheels (both of the base by default) heard from, and on in velocity mode (their
        drives answered so)."""
        for name in names or ("wl", "wr"):
            driver = self.api.devices[name][1]
            driver.reported(now())
            for op in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
                applied(driver, plan(driver, op))


def test_the_drive_holds_the_configured_limits_and_the_slower_wheel() -> None:
    drive = IdleBase().base.drive
    assert drive.command(Twist(5.0, 0.0), 0.0, 1.0) == Twist(1.0, 0.0)  # max_linear_mps
    assert drive.command(Twist(0.0, -9.0), 0.0, 1.0) == Twist(0.0, -2.0)  # max_angular_radps
    both = drive.command(Twist(1.0, 2.0), 0.0, 1.0)  # the right wheel at 16.97 rad/s
    factor = 13.0 / ((1.0 + 2.0 * TRACK / 2) / RADIUS)
    assert both.linear == pytest.approx(factor) and both.angular == pytest.approx(2 * factor)
    unslowed = IdleBase(wl=LEFT).base.drive.command(Twist(1.0, 2.0), 0.0, 1.0)
    assert unslowed == Twist(1.0, 2.0)


def test_the_drive_ramps_at_the_configured_accelerations_and_each_wheel_by_its_joint() -> None:
    drive = IdleBase().base.drive
    drive.begin(0.0, Twist())
    drive.command(Twist(1.0, 0.0), 0.0, 10.0)
    assert drive.sample(0.1).linear == pytest.approx(2.0 * 0.1)  # max_linear_accel
    left, right = drive.sampler(0)(0.2), drive.sampler(1)(0.2)
    forward = 2.0 * 0.2 / RADIUS  # rad/s of either wheel
    (field, left_rpm), = left.items()
    assert left_rpm == pytest.approx(forward / math.tau * 60, abs=0.5)
    assert right == {field: pytest.approx(-left_rpm, abs=0.5)}  # the right one is mirrored
    drive.begin(0.0, Twist())
    drive.command(Twist(0.0, 2.0), 0.0, 10.0)
    assert drive.sample(0.1).angular == pytest.approx(6.0 * 0.1)  # max_angular_accel


def test_the_odometry_takes_the_configured_wheel_radius_and_track() -> None:
    odometry = IdleBase().base.odometry
    odometry.take(0.0, 0.0, 0.0)
    odometry.take(1.0, 1.0, 1.0)
    assert odometry.pose.x == pytest.approx(RADIUS) and odometry.pose.theta == 0.0
    odometry.take(0.0, 2.0, 2.0)  # the left wheel back a radian, the right on one more
    assert odometry.pose.theta == pytest.approx(2 * RADIUS / TRACK)


def test_the_wheels_readings_publish_odometry_and_a_claim_is_told() -> None:
    idle = IdleBase()
    for position, ts in ((0.0, 1.0), (1.0, 2.0)):
        for wheel in ("wl", "wr"):
            idle.read(wheel, position, ts)
    ((name, message),) = idle.odometry
    assert name == "base" and message["ts"] == 2.0
    assert message["x"] == pytest.approx(RADIUS) and message["linear"] == pytest.approx(RADIUS)
    reply = idle.command({"op": "claim", "client": "nav", "ttl_s": 5})
    assert reply["ok"] and reply["base"]["twist"] == {"linear": 0.0, "angular": 0.0}
    (event,) = idle.events
    assert (event.device, event.type, event.fields) == (
        "base", "claimed", {"base": "base", "client": "nav", "ttl_s": 5.0})


def test_a_refused_twist_says_why_and_require_claim_reaches_the_judge() -> None:
    bases = IdleBase().bases
    offline = bases.stream("base", Twist(0.1, 0.0), "teleop")
    assert offline["error"] == {"code": "device_timeout",
                                "message": "base base: wheel wl is offline"}
    for refused in (bases.stream("base", Twist(0.1, 0.0), "teleop", require_claim=True),
                    bases.twist("base", b'{"linear":0.1,"client":"teleop","require_claim":true}')):
        assert refused["error"]["code"] == "not_claimed"
    garbled = bases.twist("base", b'{"linear":"fast"}')
    assert garbled["error"]["code"] == "bad_command" and "linear" in garbled["error"]["message"]


def test_the_deadman_stops_only_the_base_its_leaving_client_drives() -> None:
    idle = IdleBase()
    base = idle.base
    base.drive.command(Twist(0.5, 0.0), now(), 10.0)
    base.client, base.playing_since = "teleop", now()
    idle.bases.client_left("nav")
    assert base.drive.held_until > now() and not idle.events
    idle.bases.client_left("teleop")
    assert base.drive.held_until == 0.0
    (event,) = idle.events
    assert (event.type, event.fields) == (
        "stopped", {"base": "base", "client": "teleop", "reason": "client gone"})
    idle.wheels_online()
    idle.runner.plays.start({w: base.drive.sampler(s) for s, w in enumerate(base.names)}, now())
    idle.bases.tick()  # ramping down, its twist no longer held: stopped, not stale
    assert len(idle.events) == 1 and base.playing_since is not None
    base.playing_since = None  # at rest: nothing to stop
    base.drive.command(Twist(0.5, 0.0), now(), 10.0)
    idle.bases.client_left("teleop")
    assert base.drive.held_until > now() and len(idle.events) == 1


@pytest.mark.parametrize("refused", [True, False], ids=["play-ended", "play-never-taken"])
def test_a_base_stopped_by_an_online_wheel_names_why(refused) -> None:
    idle = IdleBase()
    idle.wheels_online()
    base = idle.base
    if refused:
        idle.runner.plays.start({w: base.drive.sampler(s) for s, w in enumerate(base.names)},
                                now())
        idle.runner.plays.end_all("the bus was lost")
        why = idle.runner.plays.refusal("wl")[1]
        assert "the bus was lost" in why
    else:
        why = "left the base's play"
    base.playing_since = now() - 1.0  # long enough for the bus to have taken the play
    idle.bases.tick()
    (event,) = idle.events
    assert (event.type, event.fields) == (
        "base_stopped", {"base": "base", "wheel": "wl", "reason": why})
    assert base.playing_since is None


def test_a_wheel_disabled_by_any_client_stops_a_driving_base() -> None:
    """Rule 3: a disable, a stop any client may send, takes no wheel out of the base's play,
    and the other wheel drove on alone (an audit: the base turned on the spot for 7 s with
    ``driving`` true and no event). The next tick stops both, naming the wheel."""
    idle = IdleBase()
    idle.wheels_online()
    base = idle.base
    idle.runner.plays.start({w: base.drive.sampler(s) for s, w in enumerate(base.names)}, now())
    base.drive.command(Twist(0.2, 0.0), now(), 10.0)
    base.playing_since = now()
    idle.bases.tick()
    assert idle.events == [] and base.playing_since is not None  # both on: it drives
    wr = idle.api.devices["wr"][1]
    applied(wr, plan(wr, '{"op":"disable"}'))
    idle.bases.tick()
    (event,) = idle.events
    assert (event.type, event.fields) == ("base_stopped", {
        "base": "base", "wheel": "wr",
        "reason": "is not on in velocity mode"})
    assert base.playing_since is None


@pytest.mark.parametrize(("stops", "client", "seq", "dropped"), [
    ([("nav", 9)], "nav", 8, True),
    ([("nav", 9)], "nav", 9, True),  # numbered alike: it cannot be ordered, nothing moves
    ([("nav", 9)], "nav", 10, False),
    ([("nav", 9)], "teleop", 3, False),  # another client's count
    ([("nav", 9)], "nav", None, False),  # not numbered: not ordered by numbers
    ([("nav", None)], "nav", 3, False),  # a stop not numbered
    ([], "nav", 3, False),
    # another client's stop since, numbered or not, forgets nothing of nav's (an audit: a
    # late twist of nav's, numbered before its stop, was driven after teleop's stop)
    ([("nav", 9), ("teleop", 1)], "nav", 8, True),
    ([("nav", 9), (None, None)], "nav", 8, True),
    ([(None, 9)], None, 8, True),  # a client naming none is one too
    ([(None, 9)], "nav", 8, False),
    ([("nav", 9), ("nav", 4)], "nav", 8, False),  # its own latest stop is the one it keeps
])
def test_only_a_twist_numbered_at_or_before_its_clients_stop_is_dropped(
        stops, client, seq, dropped) -> None:
    base = IdleBase().base
    for by, number in stops:
        _note_stop(base, by, number)
    assert _sent_before_stop(base, client, seq) is dropped


def test_a_base_keeps_the_last_stop_of_its_latest_clients_only() -> None:
    base = IdleBase().base
    _note_stop(base, "nav", 9)
    for n in range(STOPS_KEPT - 1):
        _note_stop(base, f"c{n}", 1)
    assert _sent_before_stop(base, "nav", 8) and len(base.stopped_by) == STOPS_KEPT
    _note_stop(base, "nav", 10)  # renewed: now the latest
    _note_stop(base, "one-more", 1)  # the oldest, c0, is forgotten
    assert _sent_before_stop(base, "nav", 8) and not _sent_before_stop(base, "c0", 1)
    assert len(base.stopped_by) == STOPS_KEPT


def test_a_wheel_coming_online_in_another_mode_is_put_in_velocity_mode_once() -> None:
    idle = IdleBase(recorded=True)
    velocity = ("wl", {"op": "set_mode", "mode": "velocity"})
    idle.read("wl", 0.0, 1.0, mode="velocity")
    assert idle.gateway.sent == []  # online in velocity mode already
    idle.read("wl", 0.0, 2.0, online=False, mode="position")
    assert idle.gateway.sent == []  # offline: nothing to tell it
    idle.read("wl", 0.0, 3.0, mode="position")
    assert idle.gateway.sent == [velocity]
    idle.read("wl", 0.0, 4.0, mode="position")
    assert idle.gateway.sent == [velocity]  # once per time it comes online
    idle.read("wl", 0.0, 5.0, online=False)
    idle.read("wl", 0.0, 6.0, mode="torque")
    assert idle.gateway.sent == [velocity, velocity]


def test_odometry_takes_only_new_fresh_readings_of_a_position() -> None:
    idle = IdleBase()
    idle.read("wl", 0.0, 1.0)
    idle.read("wr", 0.0, 1.0)
    for position, ts, more in ((5.0, 2.0, {"stale": True}), (None, 2.0, {}), (5.0, None, {})):
        idle.read("wl", position, ts, **more)
        idle.read("wr", position, ts, **more)
    assert idle.odometry == []
    idle.read("wl", 1.0, 2.0)
    idle.read("wl", 1.0, 2.0)  # the same reading again: the one before it is kept
    idle.read("wr", 0.5, 1.5)  # the right wheel read between the left's two
    (_, message), = idle.odometry
    # the left wheel's position at 1.5 s, halfway between its readings: straight ahead
    assert message == {"base": "base", "ts": 1.5, "x": pytest.approx(0.5 * RADIUS), "y": 0.0,
                       "theta": pytest.approx(0.0, abs=1e-12),
                       "linear": pytest.approx(0.5 * RADIUS / 0.5),
                       "angular": pytest.approx(0.0, abs=1e-12),
                       "commanded": {"linear": 0.0, "angular": 0.0}}
    idle.read("wl", 1.0, 3.0, velocity=0.0)  # the left wheel at rest since 2 s
    idle.read("wr", 1.0, 2.5)
    # placed between its last two readings (at rest), not the three it had
    assert idle.odometry[-1][1]["x"] == pytest.approx(RADIUS)
    assert idle.odometry[-1][1]["theta"] == pytest.approx(0.0, abs=1e-12)


def test_a_state_repeating_a_moving_wheels_measurement_is_no_reading() -> None:
    """Rule 5: a write's acknowledgement restamps a wheel's state with the last heartbeat's
    values; taken as a reading at its ``ts``, it paired one wheel's fresh position with the
    other's stale one (a false turn going straight) and published odometry at each write,
    stamped with the write's time. A wheel measured at rest holds its position: its repeats
    are readings, so a base at rest goes on publishing."""
    idle = IdleBase()
    for wheel in ("wl", "wr"):
        idle.read(wheel, 0.0, 1.0, velocity=1.0)
    idle.read("wl", 0.1, 1.1, velocity=1.0)  # a heartbeat
    idle.read("wr", 0.0, 1.105, velocity=1.0)  # a write acknowledged: the old values again
    idle.read("wl", 0.1, 1.11, velocity=1.0)
    assert idle.odometry == []
    idle.read("wr", 0.1, 1.1, velocity=1.0)  # its heartbeat, read with the left's
    (_, message), = idle.odometry
    assert message["ts"] == 1.1 and message["theta"] == 0.0
    assert message["x"] == pytest.approx(0.1 * RADIUS)
    for wheel in ("wl", "wr"):
        idle.read(wheel, 0.1, 1.2, velocity=0.0)  # stopped there
        idle.read(wheel, 0.1, 1.3, velocity=0.0)  # and still there
    assert [m["ts"] for _, m in idle.odometry] == [1.1, 1.2, 1.3]
    assert idle.odometry[-1][1]["x"] == pytest.approx(0.1 * RADIUS)


def test_a_wheels_counter_set_back_re_bases_it_and_the_pose_keeps_what_it_had() -> None:
    """Rule 5: a drive that rebooted counts from 0 again (its counter was at -46.6 rad); a
    jump no turn of the wheel makes (its top speed, 1000 rpm, turns it 1.15 rad in 11 ms) is
    re-based, not integrated, and the wheel's next readings go on from where it was."""
    idle = IdleBase()
    for wheel in ("wl", "wr"):
        idle.read(wheel, -46.0, 1.0, velocity=1.0)
        idle.read(wheel, -45.9, 1.1, velocity=1.0)
    before = idle.odometry[-1][1]
    assert before["x"] == pytest.approx(0.1 * RADIUS)
    idle.read("wl", -45.8, 1.2, velocity=1.0)
    idle.read("wr", 0.0, 1.2, velocity=1.0)  # rebooted at 1.1 s: back at 0
    assert idle.odometry[-1][1]["theta"] == pytest.approx(-0.1 * RADIUS / TRACK)  # left on
    idle.read("wl", -45.7, 1.3, velocity=1.0)
    idle.read("wr", 0.2, 1.3, velocity=1.0)  # on from the reboot's 0
    after = idle.odometry[-1][1]
    assert after["x"] == pytest.approx(0.3 * RADIUS, abs=1e-3)
    assert after["theta"] == pytest.approx(0.0, abs=1e-12)  # as far on both, since the reboot
    idle.read("wl", -44.6, 1.311, velocity=1.0)  # 1.1 rad in 11 ms: a turn its drive makes
    idle.read("wr", 1.3, 1.311, velocity=1.0)
    assert idle.odometry[-1][1]["x"] == pytest.approx(after["x"] + 1.1 * RADIUS)


def test_two_readings_dated_nearly_together_are_motion_not_a_counter_set_back() -> None:
    """Rule 5: a bus thread held up takes two heartbeats of a wheel in one look and dates
    them 1 ms apart, though 20 ms passed between them; the half radian the wheel turned is
    integrated (``READING_DATE_SLACK_S``), not re-based as a jump no drive makes."""
    idle = IdleBase()
    for wheel in ("wl", "wr"):
        idle.read(wheel, 0.0, 1.0, velocity=25.0)
        idle.read(wheel, 0.5, 1.001, velocity=25.0)
    assert idle.odometry[-1][1]["x"] == pytest.approx(0.5 * RADIUS)


def test_a_wheel_is_placed_between_its_last_two_readings_only() -> None:
    stopped = ((0.0, 1.0), (1.0, 2.0), (1.0, 3.0))  # on, then at rest
    assert _at(stopped[-2:], 2.5) == 1.0
    assert _at(((0.0, 1.0), (1.0, 2.0)), 1.5) == pytest.approx(0.5)
    assert _at(((0.0, 1.0), (1.0, 3.0)), 2.5) == pytest.approx(0.75)
    assert _at(((0.0, 1.0), (1.0, 2.0)), 3.0) == 1.0  # past the latest: never beyond it
    assert _at(((0.0, 1.0), (1.0, 2.0)), 0.5) == 0.0  # before the earlier: that one
    assert _at(((4.0, 2.0),), 1.0) == 4.0


@pytest.mark.parametrize("op", ["enable", "disable"])
def test_power_is_both_wheels_stages_in_order_as_the_requester(op) -> None:
    idle = IdleBase(recorded=True)
    drive = idle.base.drive
    drive.command(Twist(0.2, 0.0), now(), 10.0)
    reply = idle.command({"op": op, "client": "nav", "require_claim": True})
    who = {"client": "nav", "require_claim": True}
    stages = ([{"op": "set_mode", "mode": "velocity"}, {"op": "velocity", "rpm": 0},
               {"op": "enable"}] if op == "enable" else [{"op": "disable"}])
    assert idle.gateway.sent == [(wheel, stage | who) for stage in stages
                                 for wheel in ("wl", "wr")]
    assert reply["ok"] and reply["base"]["name"] == "base"
    assert (drive.held_until == 0.0) is (op == "disable")  # a disable stops the twist too
    idle.gateway.sent.clear()
    idle.command({"op": op})
    assert idle.gateway.sent[-1] == ("wr", stages[-1] | {"require_claim": False})


def test_power_answers_the_first_refusal_of_its_wheels() -> None:
    idle = IdleBase(recorded=True)
    refusals = {"wl": {"ok": False, "error": {"code": "claimed", "message": "wl is nav's"}},
                "wr": {"ok": False, "error": {"code": "claimed", "message": "wr is nav's"}}}
    idle.gateway.answer = lambda device, fields: (
        refusals[device] if fields["op"] == "enable" else {"ok": True})
    assert idle.command({"op": "enable"}) == refusals["wl"]
    idle.gateway.answer = lambda device, fields: (
        refusals[device] if device == "wr" else {"ok": True})
    assert idle.command({"op": "disable"}) == refusals["wr"]


def test_tick_looks_at_every_base_and_gives_a_new_play_time_to_be_taken() -> None:
    mirrored = LEFT | {"scale": -LEFT["scale"]}
    idle = IdleBase((BASE, BASE | {"name": "b2", "left": "w3", "right": "w4"}),
                    w3=LEFT | {"name": "w3"}, w4=mirrored | {"name": "w4"})
    idle.wheels_online(*idle.api.devices)
    b2 = idle.bases.bases["b2"]
    b2.drive.command(Twist(0.2, 0.0), now(), 10.0)
    b2.playing_since = now()  # just handed to the bus: not in its play yet
    idle.bases.tick()
    assert idle.events == [] and b2.playing_since is not None
    b2.playing_since = now() - 1.0  # long since: its wheels left the play
    idle.bases.tick()  # the first base, at rest, is passed over
    assert [(e.device, e.type) for e in idle.events] == [("b2", "base_stopped")]


def test_a_base_at_rest_lets_its_wheels_hold_and_a_stale_stream_is_told_once(monkeypatch):
    idle = IdleBase()
    idle.wheels_online()
    stopped: list[tuple[str, bool]] = []
    monkeypatch.setattr(idle.runner, "stop_playing",
                        lambda device, *, speed: stopped.append((device, speed)))
    base, drive = idle.base, idle.base.drive
    base.client, base.playing_since = "teleop", now()
    drive.command(Twist(0.2, 0.0), now() - 1.0, 0.5)  # held until half a second ago
    drive.begin(now(), Twist(0.2, 0.0))
    drive.sample(0.02)  # ramping down
    idle.bases.tick()
    idle.bases.tick()
    (stale,) = idle.events
    assert (stale.type, stale.fields) == ("stream_stale", {"base": "base", "client": "teleop"})
    assert stopped == [] and base.playing_since is not None
    for slot in range(2, 40):
        drive.sample(slot * 0.02)
    idle.bases.tick()  # at rest for two slots: both wheels keep their 0 rpm, no ramp
    assert stopped == [("wl", False), ("wr", False)] and base.playing_since is None
