"""Paired benchmark runs: this checkout against another (an earlier commit), turn about.

    .venv/bin/python tests/benchmarks/paired.py OTHER_CHECKOUT [--pairs 3] [--seconds 4] [--only P]

Each case runs ``busgate bench`` on the simulator from the other checkout's venv, then from
this one's, ``--pairs`` times, so both meet the same machine load; the medians of each side and
their difference are printed. A change counts as a regression only beyond the spread of the
runs of one side. The other checkout needs its own venv (``.venv``, with ``pip install -e``);
an older bench that named the protocol ``--kind`` is called that way.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[2]

#: (name, bench arguments after the protocol)
CASES = [
    ("inspire_la", ["--ids", "1,2,3", "--follow-period-ms", "10", "--poll-hz", "20"]),
    ("inspire_la", ["--ids", "1,2,3", "--follow-period-ms", "0", "--poll-hz", "1000"]),
    ("ds_servo", ["--ids", "1,2,3", "--follow-period-ms", "10", "--poll-hz", "20"]),
    ("zlac706_can", ["--follow-period-ms", "20", "--poll-hz", "10"]),
]
FIGURES = ["frames_out_per_s", "follow_error_p50_ms", "follow_error_p99_ms",
           "cpu_percent_bus_thread", "cpu_percent_process", "timeouts",
           "skipped_polls"]  # fmt: skip


def bench(checkout: Path, protocol: str, arguments: list[str], seconds: float) -> dict:
    python = checkout / ".venv" / "bin" / "python"
    base = [str(python), "-m", "busgate.gateway.cli", "bench", "--json", "--seconds", str(seconds)]
    for flag in ("--protocol", "--kind"):
        result = subprocess.run(
            [*base, flag, protocol, *arguments],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=checkout,
        )
        if result.returncode == 0:
            return json.loads(result.stdout)
        if "unrecognized arguments" not in result.stderr and "required" not in result.stderr:
            break
    raise SystemExit(f"{checkout}: bench {protocol} failed: {result.stderr.strip()}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("other", type=Path, help="the checkout to compare with")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--only", choices=[name for name, _ in CASES], help="one case")
    args = parser.parse_args()
    for protocol, arguments in CASES:
        if args.only not in (None, protocol):
            continue
        runs: dict[str, list[dict]] = {"other": [], "this": []}
        for _ in range(args.pairs):
            runs["other"].append(bench(args.other, protocol, arguments, args.seconds))
            runs["this"].append(bench(HERE, protocol, arguments, args.seconds))
        print(f"{protocol} {' '.join(arguments)} ({args.pairs} pairs of {args.seconds:g} s)")
        for figure in FIGURES:
            sides = {name: [run[figure] for run in side] for name, side in runs.items()}
            if None in sides["other"] + sides["this"]:
                continue  # a figure this case has none of (follow error without a stream)
            other, this = (statistics.median(sides[name]) for name in ("other", "this"))
            print(
                f"  {figure:24} other {other:9.3f} {sides['other']}  this {this:9.3f} "
                f"{sides['this']}  diff {this - other:+.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
