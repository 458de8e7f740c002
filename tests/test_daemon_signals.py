"""``busgate run`` stopped by a signal, as a real process: SIGHUP (a terminal or an ssh session
that closes, a habitual ``kill -HUP``) stops it in order as SIGTERM does, each device put in
its safe state, and says which signal it was; it ended the daemon at once before (exit status
129, no log line, a ZLAC706 left enabled)."""

from __future__ import annotations

import signal

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from tests.conftest import unused_loopback_port
from tests.gateway_process import TIMEOUT_S, GatewayProcess, serial_bus, write_config
from tests.wire_frames import received


def test_sighup_stops_the_daemon_in_order_as_sigterm_does(tmp_path) -> None:
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600).start()
    endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    config = write_config(
        tmp_path / "gw.toml", endpoint, serial_bus("uart0", simulator.port, "la1"), workers=1
    )
    gateway = GatewayProcess(config)
    try:
        gateway.wait_for("serving 1 bus, 1 up")
        mark = len(simulator.recorder.received())
        gateway.process.send_signal(signal.SIGHUP)
        assert gateway.process.wait(timeout=TIMEOUT_S) == 0
        gateway.wait_for("SIGHUP: stopping")
        gateway.wait_for("gateway gw1 stopped")
        stops = [
            frame
            for _, frame in received(simulator, mark, la)
            if isinstance(frame, la.ControlCommand) and frame.code is la.ControlCode.ESTOP
        ]
        assert stops, "the device was not put in its safe state"
    finally:
        gateway.stop()
        simulator.stop()
