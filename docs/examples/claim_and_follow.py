"""Claim an actuator and stream a sine to it for a few seconds, then let go.

While the claim holds, other clients' motion commands to la1 are refused (``claimed``); it
is renewed in the background and released when the block ends. The follow stream ends
explicitly when its block does, so no ``stream_stale`` event is raised.

    python docs/examples/claim_and_follow.py [ENDPOINT] [SECONDS]
"""

import math
import sys
import time

import busgate.client as bc

endpoint = sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 5.0
with bc.connect(endpoint, client_id="example-follow") as c:
    la1 = c.device("la1")
    with la1.claim(ttl_s=2.0), la1.follow() as stream:
        start = time.monotonic()
        while (t := time.monotonic() - start) < seconds:
            stream.set(position=round(1000 + 600 * math.sin(2 * math.pi * 0.5 * t)))
            time.sleep(0.02)  # the gateway sends the latest target at la1's follow period
    state = la1.state()
    print(f"streamed {seconds:g} s; la1 at {state.position} (target {state.target})")
