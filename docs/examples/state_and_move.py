"""Read a device's state and move it: the smallest busgate program.

Against `busgate demo` (another terminal): python docs/examples/state_and_move.py
(an endpoint as the first argument reaches another gateway or router).
"""

import sys

import busgate.client as bc

endpoint = sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"
with bc.connect(endpoint, client_id="example-move") as c:
    la1 = c.device("la1")  # a bare name: the one gateway that has it
    before = la1.state()
    print(f"{la1.gateway}/{la1.name} ({la1.kind}) at {before.position}, read at {before.ts:.3f}")
    reply = la1.move(1500)
    print("target now", reply["state"]["target"])
    try:
        la1.move(5000)  # outside 0-2000: refused, nothing moves
    except bc.OutOfRangeError as refused:
        print("refused:", refused.code)
