"""How many cores the gateway's process may use: what ``[gateway] workers = "auto"`` counts.

The cores it may run on (``os.sched_getaffinity``) are not all it may use: a container given
``--cpus 2``, or a unit with ``CPUQuota=200%``, gets a share of every core's time from its
control group, and more workers than that share only take turns. So the count is the least of
the cores it may run on and its control group's CPU quota, rounded up, along the group and its
ancestors: cgroup v2's ``cpu.max`` (``QUOTA PERIOD``, or ``max PERIOD`` for none), or v1's
``cpu.cfs_quota_us`` and ``cpu.cfs_period_us`` (a quota of -1 for none). Whatever cannot be
read counts as no quota.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

#: Where the control groups are mounted.
CGROUP_ROOT = Path("/sys/fs/cgroup")
#: Which control groups this process is in: ``ID:CONTROLLERS:PATH`` a line (v2: ``0::PATH``).
MEMBERSHIP = Path("/proc/self/cgroup")


def usable_cores(root: Path = CGROUP_ROOT, membership: Path = MEMBERSHIP) -> int:
    """The cores this process may run on, fewer when its control group's quota allows less;
    at least one."""
    cores = len(os.sched_getaffinity(0))
    quota = quota_cpus(root, membership)
    return cores if quota is None else max(1, min(cores, math.ceil(quota)))


def quota_cpus(root: Path = CGROUP_ROOT, membership: Path = MEMBERSHIP) -> float | None:
    """The CPUs' worth of time this process's control groups allow it (the least along each
    group and its ancestors), ``None`` when none sets a quota or none can be read."""
    try:
        lines = membership.read_text().splitlines()
    except OSError:
        return None
    quotas = []
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, path = fields
        if controllers == "":  # v2: one hierarchy
            quotas += [_v2_quota(d) for d in _up_to(root, root / path.lstrip("/"))]
        elif "cpu" in controllers.split(","):  # v1: the cpu controller's hierarchy
            base = root / controllers
            quotas += [_v1_quota(d) for d in _up_to(base, base / path.lstrip("/"))]
    found = [quota for quota in quotas if quota is not None]
    return min(found, default=None)


def _up_to(top: Path, start: Path) -> list[Path]:
    """``start`` and each folder above it up to ``top``."""
    folders = [start]
    while folders[-1] != top and top in folders[-1].parents:
        folders.append(folders[-1].parent)
    return folders


def _v2_quota(folder: Path) -> float | None:
    try:
        quota, period = (folder / "cpu.max").read_text().split()
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError, ZeroDivisionError):
        return None


def _v1_quota(folder: Path) -> float | None:
    try:
        quota = int((folder / "cpu.cfs_quota_us").read_text())
        period = int((folder / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 else quota / period
    except (OSError, ValueError, ZeroDivisionError):
        return None
