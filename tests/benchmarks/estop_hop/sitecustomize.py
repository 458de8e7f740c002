"""``bench_scale.py --estop-hop``'s probe, put first on the daemons' ``PYTHONPATH``: each e-stop
callback of the gateway's zenoh bridge notes when it began (``time.perf_counter``, the clock of
every process of the host), after the callback, in the file ``BUSGATE_ESTOP_HOP`` names.

Not part of busgate: Python imports a ``sitecustomize`` module at start-up when one is on its
path, and only ``bench_scale`` puts this folder there, for the daemons it starts. Their workers
inherit it and are left alone (``python -m busgate.gateway.cli run``: ``run`` is the first
argument Python has kept by then).
"""

import os
import sys
import time

_NOTES = os.environ.get("BUSGATE_ESTOP_HOP")
if _NOTES and sys.argv[1:2] == ["run"]:
    from busgate.gateway.api import bridge as _bridge

    _on_estop = _bridge.ZenohBridge._on_estop

    def _noted(self, sample, _callback=_on_estop):
        began = time.perf_counter()
        try:
            return _callback(self, sample)
        finally:
            with open(_NOTES, "a") as notes:
                notes.write(f"{began}\n")

    _bridge.ZenohBridge._on_estop = _noted
