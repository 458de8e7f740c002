"""Which buses go to which bus worker (docs/workers.md): ``[gateway] workers`` on this host's
cores, the buses a worker may run, and the busiest first onto the least loaded. Pure but for
the cores asked of the host, so that ``check-config`` tells the placement without loading
the workers' supervisor."""

from __future__ import annotations

from busgate.gateway.service.budget import bus_budget
from busgate.gateway.service.cores import usable_cores
from busgate.schemas.config import Config


def worker_count(setting: str | int, buses: int) -> int:
    """How many workers ``[gateway] workers`` makes of ``buses`` buses a worker may run:
    ``"auto"`` is one per core this process may use (``cores``), at most one per bus; one
    (or a single bus) is none: the buses run in the gateway's own process."""
    cores = usable_cores() if setting == "auto" else int(setting)
    count = min(cores, buses)
    return count if count > 1 else 0


def movable(config: Config) -> list[str]:
    """The buses a worker may run: not one on python-can's ``virtual`` interface (it exists
    within one process: the simulators' and the tests'), nor a base's (both wheels' ticks
    sample the base's live twist, in the gateway's process)."""
    wheels = {name for base in config.bases for name in (base.left, base.right)}
    return [
        bus.name
        for bus in config.buses
        if getattr(bus, "interface", None) != "virtual"
        and not wheels & {device.name for device in bus.devices}
    ]


def placement(config: Config) -> list[list[str]]:
    """The buses of each worker ``[gateway] workers`` makes of ``config`` on this host, in
    order; none: every bus runs in the gateway's own process."""
    names = movable(config)
    count = worker_count(config.gateway.workers, len(names))
    return split(config, names, count) if count else []


def too_many(workers: int) -> str | None:
    """Why ``workers`` workers are more than this host's cores serve (``check-config`` and
    ``busgate run`` say it), ``None`` when they are not."""
    cores = usable_cores()
    if workers <= cores:
        return None
    return (
        f"gateway.workers: {workers} workers on this host's {cores} core(s) take turns on "
        'them; "auto" makes one a core'
    )


def split(config: Config, names: list[str], count: int) -> list[list[str]]:
    """The buses ``names`` (``movable``) in ``count`` workers: the busiest first onto the least
    loaded, by what the config's traffic takes of each bus's wire (its budget)."""
    load = {bus.name: bus_budget(bus).wire_share for bus in config.buses if bus.name in names}
    workers: list[list[str]] = [[] for _ in range(count)]
    loads = [0.0] * count
    for name in sorted(load, key=lambda n: -load[n]):
        least = loads.index(min(loads))
        workers[least].append(name)
        loads[least] += load[name]
    return [sorted(w) for w in workers if w]
