"""The fleet on one machine: how fast a fleet e-stop reaches every device through the router,
what the dashboard costs, and how long its page takes to draw.

Not a test (pytest does not collect it). Everything runs on this machine, on 127.0.0.1 with
multicast scouting off (``tests.fleet``): ``busgate router``, ``--gateways`` gateways joining
it (``busgate demo --connect``, each a process with its own simulated devices of every kind,
recording what they receive), ``busgate dashboard`` connected to the router, Debian's
Chromium on the page (``tests.browser``), the client here; every process started and ended by
its PID. On a 2-core machine the gateways' processes alone (their simulators in them) take
most of a core, and the browser the better part of another: what is measured shares them.

    .venv/bin/python tests/benchmarks/bench_fleet.py [--gateways 3] [--trials 20]
                                                    [--seconds 10] [--synthetic 8] [--kills 5]

1. Fleet e-stop: every device enabled and still, then an e-stop of the fleet, ``--trials``
   times each way, the ways taking turns: by the SDK's put (``Client.estop()``) with no page
   open (the baseline), by the same put with the page open, and by the page's button (its
   click event, sent through the browser's DevTools protocol: Playwright's own click first
   waits for the button to stand still over a few animation frames). For each trial, the time
   to the last device's e-stop frame (every device of every gateway stopped), and for each bus
   of each gateway to its first device's; p50/p99/max in ms. Times are the wire records'
   (perf_counter: one clock for every process here).
2. The dashboard at full telemetry rate: every Inspire LA and DS servo of every gateway
   following a sine (a follow stream at 50 Hz each, under a claim), the page open, for
   ``--seconds``: the states per second the gateways published (counted by a subscriber
   here), the dashboard process's CPU (utime + stime from /proc, % of one core) and the page's
   redraws (its ``render`` every 100 ms, charts drawn: time p50/p99, and redraws per second).
3. A gateway killed with SIGKILL, ``--kills`` times: the time until its card leaves the page
   (its liveliness token gone at the router), and, restarted, until its 7 devices are back.
4. The page alone with more than 50 devices: a router, the dashboard and the page, with
   ``--synthetic`` gateways of 7 devices whose states (a sine at 20 Hz each) come from one
   zenoh session here (``SyntheticGateways``: telemetry only, no simulators to share the
   cores with): the page's redraws and the dashboard's CPU.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.fleet

import zenoh

import busgate.client as bc
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import cpu_s
from busgate.schemas.zenoh_session import session_config
from tests.browser import browser_page
from tests.fleet import Fleet, running_fleet

MOVERS = ["la1", "la2", "la3", "servo1", "servo2"]  # position-followed devices of a demo
SINE_HZ = 0.5
FOLLOW_EVERY_S = 0.02


def figures(values: list[float], unit: str = "ms", scale: float = 1000.0) -> str:
    ordered = sorted(values)
    p50, p99 = percentile(ordered, 0.5), percentile(ordered, 0.99)
    assert p50 is not None and p99 is not None
    return (f"p50 {p50 * scale:.2f} {unit}, p99 {p99 * scale:.2f} {unit}, "
            f"max {ordered[-1] * scale:.2f} {unit} (n={len(ordered)})")


def devices_of(client: bc.Client) -> list[str]:
    return [f"{d.gateway}/{d.name}" for d in client.devices(timeout=2.0)]


def wait_until(condition, what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.02)


def enable_all(client: bc.Client, names: list[str]) -> None:
    """Every device re-enabled (an enable is no idempotent write, so it is not retried by the
    gateway: on this loaded machine a simulator's reply now and then comes too late)."""
    for name in names:
        for attempt in range(3):
            try:
                client.device(name).enable()
                break
            except bc.DeviceTimeoutError:
                if attempt == 2:
                    raise
    wait_until(lambda: not any(client.device(n).state(max_age=0.5).estopped for n in names),
               "every device enabled again")


def estop_once(fleet: Fleet, client: bc.Client, page) -> dict[tuple[str, str, int], float]:
    """One fleet e-stop, by the page's button (``page``) or the SDK's put (``None``): each
    device's e-stop frame, as seconds after it was asked."""
    expected = fleet.expected_stops()
    started = time.perf_counter()
    if page is not None:  # the click event itself: Playwright's own click first waits for
        # the button to stand still over animation frames, tens of ms on a loaded page
        page.evaluate("() => document.getElementById('estop-fleet').click()")
    else:
        client.estop()
    try:
        wait_until(lambda: set(fleet.estop_frames_after(started)) == expected,
                   "an e-stop frame on every device")
    except TimeoutError:
        missing = sorted(expected - set(fleet.estop_frames_after(started)))
        raise TimeoutError(f"no e-stop frame on the wire of {missing}") from None
    return {key: at - started for key, at in fleet.estop_frames_after(started).items()}


def estop_trials(fleet: Fleet, client: bc.Client, trials: int, pages: dict) -> None:
    """``trials`` e-stops of each way in ``pages`` (a name → the page to click, or ``None``
    for the SDK's put), the ways taking turns."""
    names = devices_of(client)
    to_all: dict[str, list[float]] = {how: [] for how in pages}
    to_bus: dict[str, list[float]] = {}
    for _ in range(trials):
        for how, page in pages.items():
            enable_all(client, names)
            time.sleep(0.2)  # polls going on as usual
            found = estop_once(fleet, client, page)
            to_all[how].append(max(found.values()))
            firsts: dict[tuple[str, str], float] = {}
            for (gateway, bus, _), after in found.items():
                firsts[(gateway, bus)] = min(after, firsts.get((gateway, bus), math.inf))
            for (_, bus), first in firsts.items():
                to_bus.setdefault(f"{how}: {bus}", []).append(first)
    for how, values in to_all.items():
        print(f"   {how} → every device stopped: {figures(values)}")
    for key, values in sorted(to_bus.items()):
        print(f"   {key} (its first device): {figures(values)}")
    unreadable = sum(t.unreadable for g in fleet.gateways.values() for t in g.tails.values())
    if unreadable:
        print(f"   ({unreadable} lines of the wire records did not parse)")
    enable_all(client, names)


@contextlib.contextmanager
def sines(client: bc.Client, gateways: list[str]):
    """Every mover of ``gateways`` following a sine until the block ends."""
    stop = threading.Event()
    ranges = {"la": (200, 1800), "servo": (1000, 3000)}

    def follow(name: str, phase: float) -> None:
        low, high = ranges["la" if name.split("/")[1].startswith("la") else "servo"]
        device = client.device(name)
        with device.claim(ttl_s=5.0), device.follow() as stream:
            while not stop.is_set():
                t = time.monotonic()
                value = (low + high) / 2 + (high - low) / 2 * math.sin(
                    2 * math.pi * SINE_HZ * t + phase)
                stream.set(position=round(value))
                time.sleep(FOLLOW_EVERY_S)

    threads = [threading.Thread(target=follow, args=(f"{g}/{m}", i * 0.7), daemon=True)
               for g in gateways for i, m in enumerate(MOVERS)]
    for thread in threads:
        thread.start()
    try:
        yield
    finally:
        stop.set()
        for thread in threads:
            thread.join()


def redraws(page, seconds: float) -> tuple[list[float], float]:
    """The page's redraw times (s) over ``seconds``, and its redraws per second."""
    before = page.evaluate("() => window.busgateDashboard.renders()")
    time.sleep(seconds)
    count = page.evaluate("() => window.busgateDashboard.renders()") - before
    kept = page.evaluate("() => window.busgateDashboard.renderMs()")
    return [ms / 1000 for ms in kept[-count:]], count / seconds


def full_rate(fleet: Fleet, client: bc.Client, page, seconds: float, dashboard_pid: int) -> None:
    states = [0]
    end = client.subscribe("busgate/*/dev/*/state", lambda key, body: states.__setitem__(
        0, states[0] + 1))
    with sines(client, list(fleet.gateways)):
        time.sleep(2.0)  # the streams under way
        cpu_before, started = cpu_s(f"/proc/{dashboard_pid}/stat"), time.monotonic()
        states_before = states[0]
        times, rate = redraws(page, seconds)
        elapsed = time.monotonic() - started
        cpu = (cpu_s(f"/proc/{dashboard_pid}/stat") - cpu_before) / elapsed
        published = (states[0] - states_before) / elapsed
    end()
    count = page.locator("article[data-device]").count()
    print(f"2. the dashboard at full telemetry rate ({count} devices, {len(MOVERS)} of each "
          f"gateway following a {SINE_HZ} Hz sine), {seconds:g} s:")
    print(f"   states published {published:.0f}/s; the dashboard process's CPU "
          f"{100 * cpu:.1f} % of one core")
    print(f"   page redraw {figures(times)}, {rate:.1f} redraws/s")


def gone_and_back(fleet: Fleet, page, trials: int) -> None:
    """A gateway killed (SIGKILL) until its card leaves the page, and restarted until its
    devices are all back on it."""
    gone, back = [], []
    name = next(iter(fleet.gateways))
    for _ in range(trials):
        killed = time.monotonic()
        fleet.kill_gateway(name)
        page.wait_for_function(f"() => !document.querySelector('section[data-gateway={name}]')",
                               polling=10, timeout=10_000)
        gone.append(time.monotonic() - killed)
        started = time.monotonic()
        fleet.start_gateway(name)  # returns once the demo serves
        page.wait_for_function(f"() => document.querySelectorAll('section[data-gateway={name}] "
                               f"article[data-device]').length == 7", polling=10, timeout=30_000)
        back.append(time.monotonic() - started)
    print(f"3. a gateway killed with SIGKILL, {trials} times: gone from the page {figures(gone)};"
          f" restarted, all its devices back on the page {figures(back, 's', 1.0)}")


class SyntheticGateways:
    """Gateways that are telemetry only, for the page's load without the simulators' CPU:
    ``count`` liveliness tokens and ``info`` queryables, and 7 Inspire LA states each
    following a sine at ``hz``, from one zenoh session here. What they publish is what a
    gateway publishes (the kind's fields); nothing answers a command."""

    def __init__(self, endpoint: str, names: list[str], hz: float = 20.0) -> None:
        self._session = zenoh.open(session_config(mode="client", connect=[endpoint]))
        self._names, self.hz, self._stop = names, hz, threading.Event()
        devices = [f"la{n}" for n in range(1, 8)]
        self._devices = devices
        self._held = []
        for name in names:
            info = {"ok": True, "gateway": name, "version": "synthetic",
                    "buses": [{"name": "uart0", "protocol": "inspire_la",
                               "devices": [{"name": d, "kind": "inspire_la", "id": i + 1,
                                            "state": None} for i, d in enumerate(devices)]}]}
            payload = json.dumps(info)
            self._held.append(self._session.declare_queryable(
                f"busgate/{name}/info",
                lambda query, payload=payload: query.reply(query.key_expr, payload)))
            self._held.append(self._session.liveliness().declare_token(f"busgate/{name}/alive"))
        self._thread = threading.Thread(target=self._publish, daemon=True)
        self._thread.start()

    def _publish(self) -> None:
        while not self._stop.wait(1 / self.hz):
            now = time.time()
            for g, name in enumerate(self._names):
                for d, device in enumerate(self._devices):
                    position = round(1000 + 800 * math.sin(2 * math.pi * SINE_HZ * now + g + d))
                    state = {"ts": now, "device": device, "kind": "inspire_la", "online": True,
                             "last_reply_age_s": 0.001, "stale": False, "estopped": False,
                             "enabled": True, "position": position, "target": position,
                             "current_ma": 100 + position // 20, "temperature_c": 30,
                             "force_g": 0, "faults": [], "power": "on"}
                    self._session.put(f"busgate/{name}/dev/{device}/state", json.dumps(state))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._session.close()


def many_on_page(folder: Path, count: int, seconds: float) -> None:
    """The page alone: a fleet of ``count`` synthetic gateways, no simulators."""
    names = [f"synthetic{n}" for n in range(1, count + 1)]
    with running_fleet(folder, []) as fleet:
        synthetic = SyntheticGateways(fleet.router, names)
        try:
            with browser_page(fleet.dashboard) as page:
                page.wait_for_function("([n]) => document.querySelectorAll("
                                       "'article[data-device]').length == n",
                                       arg=[7 * count], timeout=60_000)
                time.sleep(2.0)
                cpu_before, started = cpu_s(f"/proc/{fleet.dashboard_pid}/stat"), time.monotonic()
                times, rate = redraws(page, seconds)
                elapsed = time.monotonic() - started
                cpu = (cpu_s(f"/proc/{fleet.dashboard_pid}/stat") - cpu_before) / elapsed
        finally:
            synthetic.close()
    print(f"4. the page alone with {7 * count} devices ({count} synthetic gateways, 7 states "
          f"each at {synthetic.hz:g} Hz: {7 * count * synthetic.hz:.0f}/s), {seconds:g} s:")
    print(f"   page redraw {figures(times)}, {rate:.1f} redraws/s; the dashboard process's "
          f"CPU {100 * cpu:.1f} % of one core")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gateways", type=int, default=3)
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--synthetic", type=int, default=8)
    parser.add_argument("--kills", type=int, default=5)
    args = parser.parse_args()
    names = [f"gw{n}" for n in range(1, args.gateways + 1)]
    with tempfile.TemporaryDirectory() as folder, \
            running_fleet(Path(folder), names) as fleet, \
            bc.connect(fleet.router, client_id="bench-fleet") as client:
        wait_until(lambda: len(devices_of(client)) == 7 * len(names), "every gateway up")
        print(f"1. fleet e-stop, {args.trials} trials of each way, {len(names)} gateways × 7 "
              f"devices, through the router (ms from the ask to the frame on the wire):")
        estop_trials(fleet, client, args.trials, {"put, no page open": None})
        with browser_page(fleet.dashboard) as page:
            page.wait_for_function("([n]) => document.querySelectorAll('article[data-device]')"
                                   ".length == n", arg=[7 * len(names)], timeout=60_000)
            estop_trials(fleet, client, args.trials, {"put, page open": None, "button": page})
            full_rate(fleet, client, page, args.seconds, fleet.dashboard_pid)
            gone_and_back(fleet, page, args.kills)
    with tempfile.TemporaryDirectory() as folder:
        many_on_page(Path(folder), args.synthetic, args.seconds)


if __name__ == "__main__":
    main()
