"""The cores `sampling = "auto"` counts: affinity capped by a cgroup's CPU quota."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from agent_client.training.sampling.cores import cpu_quota, usable_cores


def write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_cgroup_v2_takes_the_tightest_quota_on_the_way_to_the_root(tmp_path: Path) -> None:
    write(tmp_path / "proc", "0::/kubepods/pod1/app\n")
    write(tmp_path / "cg/kubepods/pod1/app/cpu.max", "max 100000\n")
    write(tmp_path / "cg/kubepods/pod1/cpu.max", "250000 100000\n")  # the pod: 2.5 CPUs
    write(tmp_path / "cg/kubepods/cpu.max", "800000 100000\n")
    assert cpu_quota(tmp_path / "cg", tmp_path / "proc") == pytest.approx(2.5)


def test_cgroup_v1_reads_the_cpu_controllers_quota(tmp_path: Path) -> None:
    write(tmp_path / "proc", "4:memory:/docker/abc\n3:cpu,cpuacct:/docker/abc\n")
    write(tmp_path / "cg/cpu,cpuacct/docker/abc/cpu.cfs_quota_us", "150000\n")
    write(tmp_path / "cg/cpu,cpuacct/docker/abc/cpu.cfs_period_us", "100000\n")
    write(tmp_path / "cg/cpu,cpuacct/cpu.cfs_quota_us", "-1\n")  # the root: none
    write(tmp_path / "cg/cpu,cpuacct/cpu.cfs_period_us", "100000\n")
    assert cpu_quota(tmp_path / "cg", tmp_path / "proc") == pytest.approx(1.5)


def test_no_quota_set_or_readable_is_none(tmp_path: Path) -> None:
    write(tmp_path / "proc", "0::/\n")
    write(tmp_path / "cg/cpu.max", "max 100000\n")
    assert cpu_quota(tmp_path / "cg", tmp_path / "proc") is None
    assert cpu_quota(tmp_path / "cg", tmp_path / "missing") is None
    write(tmp_path / "garbled/cpu.max", "lots\n")
    assert cpu_quota(tmp_path / "garbled", tmp_path / "proc") is None


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity here")
def test_usable_cores_is_the_affinity_capped_by_the_quota(tmp_path: Path) -> None:
    affinity = len(os.sched_getaffinity(0))
    write(tmp_path / "proc", "0::/\n")
    write(tmp_path / "cg/cpu.max", "50000 100000\n")  # half a CPU: still one to run on
    assert usable_cores(tmp_path / "cg", tmp_path / "proc") == 1
    write(tmp_path / "cg/cpu.max", f"{100000 * (affinity + 4)} 100000\n")  # more than it has
    assert usable_cores(tmp_path / "cg", tmp_path / "proc") == affinity
