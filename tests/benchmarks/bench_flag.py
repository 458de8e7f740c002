"""What a bus thread's wake-up flag costs: ``threading.Event`` against ``flag.Flag``.

Not a test (pytest does not collect it). For each kind, turn about, ``RUNS`` times:

- a thread's CPU a wait that times out (4 ms waits, as a bus thread's idle pauses end);
- a ``set`` while another thread waits (what handing a bus thread work or an e-stop costs
  the thread that hands it over), and from that ``set`` until the waiter is back.

Medians of the runs; the figures depend on the host.

    .venv/bin/python tests/benchmarks/bench_flag.py [RUNS]
"""

from __future__ import annotations

import statistics
import threading
import time

from usage import arguments

from busgate.gateway.bus.flag import Flag

WAITS = 250
SETS = 300
KINDS = (threading.Event, Flag)


def timed_out_wait_cpu_us(kind: type) -> float:
    flag, cpu = kind(), []

    def waits() -> None:
        start = time.thread_time()
        for _ in range(WAITS):
            flag.wait(0.004)
        cpu.append((time.thread_time() - start) / WAITS)

    thread = threading.Thread(target=waits)
    thread.start()
    thread.join()
    return cpu[0] * 1e6


def set_and_back_us(kind: type) -> tuple[float, float]:
    """The median ``set`` with a waiter, and from it until the waiter is back (µs)."""
    sets, backs = [], []
    for _ in range(SETS):
        flag, back = kind(), []
        waiter = threading.Thread(target=_wait_and_note, args=(flag, back))
        waiter.start()
        time.sleep(0.002)  # it waits
        start = time.perf_counter()
        flag.set()
        sets.append(time.perf_counter() - start)
        waiter.join()
        backs.append(back[0] - start)
    return statistics.median(sets) * 1e6, statistics.median(backs) * 1e6


def _wait_and_note(flag, back: list[float]) -> None:
    flag.wait(1.0)
    back.append(time.perf_counter())


def main(runs: int) -> None:
    figures: dict[type, list[tuple[float, float, float]]] = {kind: [] for kind in KINDS}
    for _ in range(runs):
        for kind in KINDS:
            figures[kind].append((timed_out_wait_cpu_us(kind), *set_and_back_us(kind)))
    for kind, rows in figures.items():
        wait_cpu, set_cost, back = (statistics.median(column) for column in zip(*rows, strict=True))
        print(f"{kind.__name__:6s} CPU a timed-out wait {wait_cpu:5.1f} us, a set with a waiter "
              f"{set_cost:5.1f} us, set to the waiter back {back:5.1f} us")


if __name__ == "__main__":
    main(arguments(__doc__, ("runs", int, 5, "how many runs of each kind")).runs)
