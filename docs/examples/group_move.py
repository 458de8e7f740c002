"""Start several actuators of one bus together: one group frame on the wire.

python docs/examples/group_move.py [ENDPOINT]
"""

import sys

import busgate.client as bc

endpoint = sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"
targets = {"la1": 300, "la2": 900, "la3": 1500}
with bc.connect(endpoint, client_id="example-group") as c:
    uart0 = c.bus("demo/uart0")
    print(f"{uart0.gateway}/{uart0.name} speaks {uart0.protocol}")
    uart0.group_move([{"device": name, "position": p} for name, p in targets.items()])
    for name, position in targets.items():
        # The actuators report their targets in their next status reads.
        reported = next(
            (s.target for s in c.device(f"demo/{name}").states(timeout=2) if s.target == position),
            None,
        )
        print(name, "reports target", reported)
