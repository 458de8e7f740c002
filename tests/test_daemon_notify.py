"""``busgate run`` under a systemd-like supervisor: READY once the buses are open, watchdog
pings while they keep their schedule, STOPPING on SIGTERM — read off a real NOTIFY_SOCKET."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator


def test_ready_watchdog_and_stopping(free_port, tmp_path) -> None:
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600).start()
    config = tmp_path / "gw.toml"
    config.write_text(
        f'[gateway]\nname = "gw1"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n'
        f'[[buses]]\nname = "uart0"\ntransport = "serial"\nport = "{simulator.port}"\n'
        'baudrate = 921600\n[[buses.devices]]\nname = "la1"\nkind = "inspire_la"\nid = 1\n'
    )
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(15)
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "400000"}
    process = subprocess.Popen([sys.executable, "-m", "busgate.gateway.cli", "run", "--config",
                                str(config)], env=env, stderr=subprocess.DEVNULL)
    try:
        messages = []
        while not any("READY=1" in m for m in messages):
            messages.append(notify.recv(4096).decode())
        ready = next(m for m in messages if "READY=1" in m)
        assert "STATUS=gateway gw1: 1 bus(es) open" in ready
        while "WATCHDOG=1" not in messages:
            messages.append(notify.recv(4096).decode())
        process.send_signal(signal.SIGTERM)
        while not any("STOPPING=1" in m for m in messages):
            messages.append(notify.recv(4096).decode())
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
        notify.close()
        simulator.stop()
