"""How many CPU cores this process may keep busy: the fewer of its affinity (taskset, a cpuset)
and its CPU quota (a container's ``--cpus``, Kubernetes' ``limits.cpu``).

A quota does not show in the affinity: a pod limited to 2 CPUs on a 32-core node sees 32
cores it may run on, and gets 2 cores' time per second across them. `sampling = "auto"` counts
with the fewer (`TrainConfig.sampling_on`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path, PurePosixPath

CGROUP_ROOT = Path("/sys/fs/cgroup")
MEMBERSHIP = Path("/proc/self/cgroup")


def usable_cores(root: Path = CGROUP_ROOT, membership: Path = MEMBERSHIP) -> int:
    """The cores this process may run on, capped by its CPU quota (rounded down, at least 1)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform (macOS)
        cores = os.cpu_count() or 1
    quota = cpu_quota(root, membership)
    return cores if quota is None else max(1, min(cores, math.floor(quota)))


def cpu_quota(root: Path = CGROUP_ROOT, membership: Path = MEMBERSHIP) -> float | None:
    """CPU seconds per second this process's cgroups allow (the tightest from its own cgroup
    up to the root, cgroup v2 or v1); None where no quota is set or none can be read."""
    try:
        lines = membership.read_text().splitlines()
    except OSError:  # not Linux
        return None
    quotas: list[float] = []
    for line in lines:
        hierarchy, _, rest = line.partition(":")
        controllers, _, path = rest.partition(":")
        if hierarchy == "0" and not controllers:  # the v2 hierarchy
            quotas += _quotas(root, path, _v2_quota)
        elif "cpu" in controllers.split(","):  # v1's cpu controller, mounted under its names
            mounted = root / controllers
            quotas += _quotas(mounted if mounted.is_dir() else root / "cpu", path, _v1_quota)
    return min(quotas) if quotas else None


def _quotas(base: Path, path: str, read: Callable[[Path], float | None]) -> list[float]:
    """The quotas set on `path`'s cgroup and each of its ancestors under `base`."""
    parts = PurePosixPath(path).parts[1:]  # without the leading "/"
    found = [read(base.joinpath(*parts[:depth])) for depth in range(len(parts), -1, -1)]
    return [quota for quota in found if quota is not None]


def _v2_quota(folder: Path) -> float | None:
    """``cpu.max``: "max 100000" (no quota) or "QUOTA PERIOD" in microseconds."""
    try:
        quota, period = (folder / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        return None


def _v1_quota(folder: Path) -> float | None:
    """``cpu.cfs_quota_us`` (-1: no quota) over ``cpu.cfs_period_us``."""
    try:
        quota = int((folder / "cpu.cfs_quota_us").read_text())
        period = int((folder / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return None if quota <= 0 or period <= 0 else quota / period
