"""``busgate`` as a child process, the way a user or systemd starts it: ``run_busgate`` for a
command that ends (a refusal), ``GatewayProcess`` for ``busgate run`` serving until SIGTERM,
its log read line by line on a thread so that a test waits for the line it expects, and
``DemoProcess`` for ``busgate demo``, started once it printed its hints."""

from __future__ import annotations

import queue
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

TIMEOUT_S = 30.0  # a hang guard, not a speed requirement
BUSGATE = [sys.executable, "-m", "busgate.gateway.cli"]


def run_busgate(*args: str, **options) -> subprocess.CompletedProcess:
    """``busgate ARGS`` to its end: exit status, stdout and stderr as text."""
    return subprocess.run([*BUSGATE, *args], capture_output=True, text=True, timeout=TIMEOUT_S,
                          **options)


def serial_bus(name: str, port: str, device: str, *, device_id: int = 1) -> str:
    """One ``[[buses]]`` table: an Inspire LA bus at 921600 baud."""
    return (f'[[buses]]\nname = "{name}"\ntransport = "serial"\nport = "{port}"\n'
            f'baudrate = 921600\n[[buses.devices]]\nname = "{device}"\nkind = "inspire_la"\n'
            f"id = {device_id}\n")


def bus_table(name: str, port: str, baudrate: int, devices: dict[str, tuple[str, int]],
              **options: object) -> str:
    """One ``[[buses]]`` table of a serial bus with ``devices`` (name → (kind, id)) and
    ``options`` (``reply_margin_ms = 10`` …)."""
    text = (f'[[buses]]\nname = "{name}"\ntransport = "serial"\nport = "{port}"\n'
            f"baudrate = {baudrate}\n" + "".join(f"{k} = {v}\n" for k, v in options.items()))
    for device, (kind, device_id) in devices.items():
        text += f'[[buses.devices]]\nname = "{device}"\nkind = "{kind}"\nid = {device_id}\n'
    return text


def write_config(path: Path, endpoint: str, *buses: str, name: str = "gw1",
                 metrics: str | None = None, workers: int | None = None) -> Path:
    """A gateway config listening on ``endpoint`` only (and serving metrics on ``metrics``),
    with ``buses`` (``serial_bus``), in ``workers`` processes (by default, one per core)."""
    metrics_table = "" if metrics is None else f'[metrics]\nlisten = "{metrics}"\n'
    workers_line = "" if workers is None else f"workers = {workers}\n"
    path.write_text(f'[gateway]\nname = "{name}"\n{workers_line}[zenoh]\nlisten = ["{endpoint}"]\n'
                    + metrics_table + "".join(buses))
    return path


class GatewayProcess:
    """``busgate run --config FILE`` as a child; ``lines`` holds what it logged so far."""

    def __init__(self, config: Path, **options) -> None:
        self.process = subprocess.Popen([*BUSGATE, "run", "--config", str(config)],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                        text=True, **options)
        self.lines: list[str] = []
        #: Every line logged so far, read or not by ``wait_for`` (to show when a test fails).
        self.logged: list[str] = []
        self._incoming: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stderr:
            self.logged.append(line.rstrip("\n"))
            self._incoming.put(line.rstrip("\n"))
        self._incoming.put("")  # end of output

    def wait_for(self, text: str) -> str:
        """The first logged line containing ``text``; fails when the process ends first."""
        while True:
            line = self._incoming.get(timeout=TIMEOUT_S)
            assert line, f"busgate run ended before logging {text!r}: {self.lines}"
            self.lines.append(line)
            if text in line:
                return line

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout=TIMEOUT_S)


class ServingProcess:
    """``busgate ARGS`` as a child that prints on stdout until it serves (``demo``,
    ``router``, ``dashboard``), returned once a line starting with ``ready`` came; ``printed``
    holds what it printed up to it."""

    def __init__(self, *args: str, ready: str, stderr=None, within: Sequence[str] = ()) -> None:
        """``within``: what the command runs under (``ip netns exec NAME``, which execs it:
        the child's PID is busgate's own)."""
        self.process = subprocess.Popen([*within, *BUSGATE, *args], stdout=subprocess.PIPE,
                                        text=True, stderr=stderr)
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self.printed = self._wait_for(ready)

    def _read(self) -> None:
        for line in self.process.stdout:
            self._lines.put(line)
        self._lines.put("")  # end of output

    def _wait_for(self, ready: str) -> str:
        lines: list[str] = []
        while not lines or not lines[-1].startswith(ready):
            try:
                line = self._lines.get(timeout=TIMEOUT_S)
            except queue.Empty:
                self.process.kill()
                raise
            assert line, f"busgate {self.process.args[3]} ended before it served: {lines!r}"
            lines.append(line)
        return "".join(lines)

    def terminate(self, signum: int = signal.SIGTERM) -> int:
        """Stop it with ``signum`` (SIGTERM or SIGINT, as Ctrl-C): its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signum)
        return self.process.wait(timeout=TIMEOUT_S)


class DemoProcess(ServingProcess):
    """``busgate demo --listen ENDPOINT`` as a child (its dashboard on a free port, unless
    ``options`` say otherwise; with ``--connect`` among them, a client of the router there,
    listening on nothing), returned once it serves; ``hints`` holds what it printed and
    ``dashboard`` the URL it printed (``None`` without one)."""

    def __init__(self, endpoint: str, *options: str, within: Sequence[str] = (),
                 stderr=None) -> None:
        self.endpoint = endpoint
        options = options or ("--dashboard-listen", "127.0.0.1:0")
        link = () if "--connect" in options else ("--listen", endpoint)  # a router's client
        super().__init__("demo", *link, *options, ready="Ctrl-C", within=within, stderr=stderr)
        self.hints = self.printed
        shown = re.search(r"in a browser: (\S+)", self.hints)
        self.dashboard = shown.group(1) if shown else None
