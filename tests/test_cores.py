"""What ``[gateway] workers = "auto"`` counts (gateway/service/cores.py): the cores this process
may run on, fewer when its control group's CPU quota allows less, on control group trees
laid out in a temporary folder as the kernel lays them out (v2 and v1)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from busgate.gateway.service.cores import quota_cpus, usable_cores


def tree(root: Path, membership: str, files: dict[str, str]) -> Path:
    """The control group files ``files`` under ``root``, and a membership file saying
    ``membership``; the membership file's path."""
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    path = root / "self-cgroup"
    path.write_text(membership)
    return path


def test_a_v2_quota_on_the_group_or_an_ancestor_counts_the_least_rounded_up(tmp_path) -> None:
    member = tree(tmp_path, "0::/system.slice/busgate.service\n", {
        "cpu.max": "max 100000\n",  # the root: none
        "system.slice/cpu.max": "150000 100000\n",  # the slice's: one and a half CPUs' worth
        "system.slice/busgate.service/cpu.max": "300000 100000\n",  # the unit's: three
    })
    assert quota_cpus(tmp_path, member) == pytest.approx(1.5)
    cores = len(os.sched_getaffinity(0))
    assert usable_cores(tmp_path, member) == min(cores, 2)


def test_a_container_sees_its_quota_at_the_root_of_its_namespace(tmp_path) -> None:
    member = tree(tmp_path, "0::/\n", {"cpu.max": "100000 100000\n"})  # docker --cpus 1
    assert quota_cpus(tmp_path, member) == pytest.approx(1.0)
    assert usable_cores(tmp_path, member) == 1


def test_a_v1_cpu_controller_quota_counts_and_minus_one_is_none(tmp_path) -> None:
    member = tree(tmp_path, "4:memory:/x\n2:cpu,cpuacct:/docker/abc\n0::/\n", {
        "cpu,cpuacct/cpu.cfs_quota_us": "-1\n",
        "cpu,cpuacct/cpu.cfs_period_us": "100000\n",
        "cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "250000\n",
        "cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000\n",
        "memory/x/cpu.cfs_quota_us": "1000\n",  # not the cpu controller's: not read
    })
    assert quota_cpus(tmp_path, member) == pytest.approx(2.5)


@pytest.mark.parametrize("files", [
    {},  # no control group files at all
    {"cpu.max": "max 100000\n"},
    {"cpu.max": "garbage\n"},
    {"cpu.max": "100000 0\n"},
])
def test_no_quota_or_one_that_cannot_be_read_leaves_the_cores_it_may_run_on(tmp_path,
                                                                           files) -> None:
    member = tree(tmp_path, "0::/\nnot a line\n", files)
    assert quota_cpus(tmp_path, member) is None
    assert usable_cores(tmp_path, member) == len(os.sched_getaffinity(0))
    assert usable_cores(tmp_path, tmp_path / "no-such-file") == len(os.sched_getaffinity(0))
