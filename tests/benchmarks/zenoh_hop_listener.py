"""``bench_scale.py --estop-hop``'s floor: a process that does nothing but take zenoh puts.

    python tests/benchmarks/zenoh_hop_listener.py ENDPOINT NOTES

Listens on ENDPOINT (multicast scouting off), subscribes to ``bench/hop`` as the gateway's
bridge subscribes to its e-stop key (a plain callable: zenoh's thread hands each put to
Python), notes ``time.perf_counter`` (CLOCK_MONOTONIC, every process's clock on Linux) at
each callback's start in NOTES, prints ``ready`` once subscribed, and ends when its stdin
closes. A put's time to this callback is zenoh's hop with no gateway behind it, taken in the
same run and on the same host as the gateway's.
"""

import sys
import time

import zenoh

from busgate.schemas.zenoh_session import session_config

KEY = "bench/hop"


def main() -> None:
    if len(sys.argv) != 3:
        sys.exit("usage: zenoh_hop_listener.py ENDPOINT NOTES (started by bench_scale.py)")
    endpoint, notes = sys.argv[1:3]
    noted: list[float] = []
    with zenoh.open(session_config(listen=[endpoint])) as session:
        session.declare_subscriber(KEY, lambda _sample: noted.append(time.perf_counter()))
        print("ready", flush=True)
        sys.stdin.read()
    with open(notes, "w") as out:
        out.writelines(f"{t}\n" for t in noted)


if __name__ == "__main__":
    main()
