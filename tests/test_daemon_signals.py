"""``busgate run`` stopped by a signal, as a real process: SIGHUP (a terminal or an ssh session
that closes, a habitual ``kill -HUP``) stops it in order as SIGTERM does, each device put in
its safe state, and says which signal it was; it ended the daemon at once before (exit status
129, no log line, a ZLAC706 left enabled). A stop ends in time with a ``connect`` endpoint
that never answers: zenoh's close waited for it 10 s, systemd's whole ``TimeoutStopSec``."""

from __future__ import annotations

import signal
import socket
import subprocess
import time

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


def test_a_connect_endpoint_that_never_answers_holds_the_stop_one_second_at_most(
        tmp_path) -> None:
    with socket.socket() as mute:  # takes the connection, never speaks zenoh
        mute.bind(("127.0.0.1", 0))
        mute.listen()
        mute.settimeout(TIMEOUT_S)
        config = write_config(tmp_path / "gw.toml", f"tcp/127.0.0.1:{unused_loopback_port()}",
                              serial_bus("uart0", str(tmp_path / "unplugged"), "la1"), workers=1)
        config.write_text(config.read_text().replace(
            "[zenoh]\n", f'[zenoh]\nconnect = ["tcp/127.0.0.1:{mute.getsockname()[1]}"]\n'))
        gateway = GatewayProcess(config)
        try:
            gateway.wait_for("serving 1 bus")
            held, _ = mute.accept()  # zenoh's connect is under way
            with held:
                gateway.process.send_signal(signal.SIGTERM)
                signalled = time.monotonic()
                try:
                    status = gateway.process.wait(timeout=5.0)  # not zenoh's 10 s
                except subprocess.TimeoutExpired:
                    status = None
                stopped_in = time.monotonic() - signalled
            assert status == 0, f"still stopping after {stopped_in:.1f} s"
            gateway.wait_for("did not close within 1 s")
            gateway.wait_for("gateway gw1 stopped")
        finally:
            gateway.stop()
