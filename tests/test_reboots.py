"""A device that reboots under the gateway: seen from its replies or heartbeats (or
from coming back after going offline), reported with a ``rebooted`` event, its follow stream
dropped, its settings written again, and nothing sent that would move it until a fresh
command. Real bus runners against the simulators, whose ``reboot`` is a power cycle."""

from __future__ import annotations

import time

import can

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.gateway.bus.clock import now
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.ds_servo import DsServoDevice
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus, SerialBus

#: Room in each reply window for the simulators, which share this process and a loaded
#: machine's cores: a late reply must not pass for a device gone silent.
REPLY_MARGIN_MS = 50


def frames_after(simulator, moment: float) -> list:
    return [r for r in simulator.recorder.received() if r.start > moment]


def nothing_due(runner, device: str) -> bool:
    """Nothing of ``device``'s would go out by itself any more: no keep-alive is owed and no
    follow stream runs (what is left are polls, which only ask)."""
    driver = runner.drivers[device]
    keepalive = getattr(driver, "keepalive", lambda now: None)
    streams = [t for t in runner.planner.tickers if device in getattr(t, "streams", {})]
    return keepalive(now()) is None and streams == []


def test_a_zlac706_whose_position_counter_restarts_gets_its_mode_back_and_stays_put(
    wait_for
) -> None:
    channel = f"test-reboot-{time.monotonic_ns()}"
    with CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=20)],
                      bus=can.Bus(interface="virtual", channel=channel)) as simulator:
        config = CanBus(name="can0", transport="can", interface="virtual", channel=channel,
                        reply_margin_ms=REPLY_MARGIN_MS,
                        devices=[{"name": "wheel", "kind": "zlac706", "id": 1,
                                  "heartbeat_ms": 20}])
        events = []
        runner = build_bus(config, on_event=events.append).start()
        try:
            wait_for(lambda: runner.drivers["wheel"].online)
            driver = runner.drivers["wheel"]
            for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
                runner.submit("wheel", driver.parse(text)).result(10)
            full_speed = driver.follow_target({"rpm": 1000})

            def far_out_at_full_speed() -> bool:
                runner.follow("wheel", full_speed, "velocity")  # a client streaming speeds
                return abs(driver.measured["position"] or 0) > 100_000

            wait_for(far_out_at_full_speed, timeout=10)
            rebooted_at = now()
            simulator.devices[0].reboot(rebooted_at)
            wait_for(lambda: any(e.type == "rebooted" for e in events))
            wait_for(lambda: "stream_stopped" in [e.type for e in events])

            def restored() -> bool:  # the mode again, then the speed set to 0
                wires = [r.wire for r in frames_after(simulator, rebooted_at)]
                return "001#00fa00190000002f" in wires and "001#00fa001100000000" in wires

            wait_for(restored, timeout=10)
            # Instead of waiting out a keep-alive period: nothing is left to go out by itself,
            # and a command after it all was carried out (what was queued went before it).
            assert nothing_due(runner, "wheel"), "a keep-alive or a tick is still owed"
            ramp = driver.parse('{"op":"set_velocity_ramp","accel_ms":100,"decel_ms":100}')
            runner.submit("wheel", ramp).result(10)
            after = frames_after(simulator, rebooted_at)
        finally:
            runner.stop()
    writes = [r.wire for r in after if r.frame == "Write"]
    assert "001#00fa00190000002f" in writes, "velocity mode written again"
    assert "001#00fa00100000001f" not in writes, "not enabled again by the gateway"
    # A tick may go out before the next heartbeat tells of the reboot; then the stream is
    # dropped and the speed set to 0, so that an enable would not start the wheel.
    speeds = [w for w in writes if w.startswith("001#00fa0011")]
    assert speeds[-1] == "001#00fa001100000000" and len(speeds) <= 3, speeds
    assert "stream_stopped" in [e.type for e in events]


def test_a_ds_servo_switched_off_that_powers_up_is_switched_off_again(wait_for) -> None:
    with SerialSimulator(ds, [DsServoDevice(1)], baudrate=1_000_000) as simulator:
        config = SerialBus(name="uart1", transport="serial", port=simulator.port,
                           baudrate=1_000_000, reply_margin_ms=REPLY_MARGIN_MS,
                           devices=[{"name": "arm", "kind": "ds_servo", "id": 1, "poll_hz": 20}])
        events = []
        runner = build_bus(config, on_event=events.append).start()
        try:
            wait_for(lambda: runner.drivers["arm"].online)
            driver = runner.drivers["arm"]
            runner.submit("arm", driver.parse('{"op":"torque","on":false}')).result(10)
            rebooted_at = now()
            simulator.devices[0].reboot(rebooted_at)
            wait_for(lambda: any(e.type == "rebooted" for e in events))
            wait_for(lambda: driver.torque_on is False)
            # The bus went on (two more polls) after the torque went off: a move would have gone.
            settled = len(simulator.recorder.received())
            wait_for(lambda: len(simulator.recorder.received()) >= settled + 2, timeout=10)
            after = frames_after(simulator, rebooted_at)
        finally:
            runner.stop()
    torque_off = ds.encode(ds.Write(1, 0x28, b"\x00")).hex()
    assert torque_off in [r.wire for r in after]
    assert not [r for r in after if r.frame in ("SyncWrite", "Action", "RegWrite")]


def test_an_estopped_actuator_back_from_offline_is_estopped_again(wait_for) -> None:
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        config = SerialBus(name="uart0", transport="serial", port=simulator.port,
                           baudrate=921_600, reply_margin_ms=REPLY_MARGIN_MS,
                           devices=[{"name": "la1", "kind": "inspire_la", "id": 1,
                                     "poll_hz": 50}])
        runner = build_bus(config).start()
        try:
            wait_for(lambda: runner.drivers["la1"].online)
            driver = runner.drivers["la1"]
            runner.submit("la1", driver.parse('{"op":"estop"}')).result(10)
            simulator.faults.configure(silent_ids=frozenset({1}))  # power lost
            wait_for(lambda: not driver.online)
            back_at = now()
            simulator.devices[0].reboot(back_at)
            simulator.faults.configure(silent_ids=frozenset())
            wait_for(lambda: driver.online and not driver.restore_pending)
            estop = la.encode(la.ControlCommand(1, la.ControlCode.ESTOP)).hex()
            wait_for(lambda: estop in [r.wire for r in frames_after(simulator, back_at)])
            # The bus went on (three more polls) after the restore: a move would have gone.
            settled = len(simulator.recorder.received())
            wait_for(lambda: len(simulator.recorder.received()) >= settled + 3, timeout=10)
            after = frames_after(simulator, back_at)
        finally:
            runner.stop()
    assert estop in [r.wire for r in after][:6], "e-stopped again as it comes back"
    assert not [r for r in after if r.frame in ("MoveCommand", "FollowCommand")]
