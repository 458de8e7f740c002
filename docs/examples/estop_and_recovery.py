"""E-stop a gateway, see motion refused, then recover the devices.

A gateway e-stop stops every device at once and latches: motion is refused (``estopped``)
until a device gets its re-enable command (``Device.enable``), or a reset brings it back to
the power state it had, holding still (``Device.reset_estop``; ``c.reset_estop(gateway)``
for every device of the gateway). ``c.estop()`` with no gateway stops the whole fleet.

    python docs/examples/estop_and_recovery.py [ENDPOINT]
"""

import sys
import time

import busgate.client as bc

endpoint = sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"
with bc.connect(endpoint, client_id="example-estop") as c:
    la1, servo = c.device("la1"), c.device("servo1")
    c.estop("demo")
    deadline = time.monotonic() + 2.0
    while not la1.state(max_age=0).estopped and time.monotonic() < deadline:
        pass  # each state() waits for the next state message
    try:
        la1.move(800)
    except bc.EstoppedError as refused:
        print("refused:", refused.message)
    for device in (la1, servo):
        device.enable()  # the kind's own re-enable command
    print("la1 moves again:", la1.move(800)["ok"])
    c.reset_estop("demo")  # the demo's other devices too, each holding still
    print("demo reset")
