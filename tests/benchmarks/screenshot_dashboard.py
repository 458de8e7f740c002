"""The README's picture of the dashboard: ``busgate demo`` (a child process, on a free
loopback port, its dashboard on another), three of its devices moving for ``--seconds`` (a
claim, a follow stream of a sine on la1, moves of la2 and servo1) while its base drives an
arc, then the page as Debian's Chromium draws it (``tests.browser``), saved as a PNG.

    .venv/bin/python tests/benchmarks/screenshot_dashboard.py [--out docs/dashboard.png]
                                                             [--seconds 12]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.*

import busgate.client as bc
from tests.browser import browser_page
from tests.conftest import unused_loopback_port
from tests.gateway_process import DemoProcess

ROOT = Path(__file__).resolve().parents[2]
MOVE_EVERY_S = 4.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png")
    parser.add_argument("--seconds", type=float, default=12.0)
    args = parser.parse_args()
    demo = DemoProcess(f"tcp/127.0.0.1:{unused_loopback_port()}")
    try:
        with bc.connect(demo.endpoint, client_id="screenshot") as client, \
                browser_page(demo.dashboard, width=1400, height=900) as page:
            la1, la2, servo1 = (client.device(n) for n in ("la1", "la2", "servo1"))
            base = client.base("base")
            base.enable()
            started, moves = time.monotonic(), 0
            with la1.claim(ttl_s=2.0), la1.follow() as stream, base.drive_stream() as drive:
                while (elapsed := time.monotonic() - started) < args.seconds:
                    stream.set(position=round(1000 + 700 * math.sin(elapsed * 1.2)))
                    drive.send(0.3, 0.4)
                    if elapsed >= moves * MOVE_EVERY_S:  # now and then, a move the other way
                        la2.move(1800 if moves % 2 == 0 else 300)
                        servo1.move(3200 if moves % 2 == 0 else 1000)
                        moves += 1
                    time.sleep(0.02)
            time.sleep(0.5)
            page.screenshot(path=str(args.out))
    finally:
        demo.terminate()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
