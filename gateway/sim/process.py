"""A simulator in a child process (``busgate sim``), for benchmarks and tests that must not
share a CPU budget or the GIL with the gateway they measure."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence

from busgate.errors import BusUnavailableError

START_TIMEOUT_S = 20.0


class SimProcess:
    """``busgate sim <protocol> …`` running as a child; ``port`` is the path it printed."""

    def __init__(self, protocol: str, arguments: Sequence[str] = ()) -> None:
        command = [sys.executable, "-m", "busgate.gateway.cli", "sim", protocol, *arguments]
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
        line = self.process.stdout.readline() if self.process.stdout else ""
        if not line.startswith("PORT "):
            self.stop()
            raise BusUnavailableError(f"the simulator did not start: {line!r}")
        self.port = line.removeprefix("PORT ").strip()

    def stop(self) -> int:
        """SIGTERM, then wait; return the exit status."""
        if self.process.poll() is None:
            self.process.terminate()
        try:
            return self.process.wait(timeout=START_TIMEOUT_S)
        finally:
            if self.process.stdout:
                self.process.stdout.close()

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
