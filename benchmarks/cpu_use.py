"""Where the CPU goes: the processes of a measurement by role, each one's CPU time per env step.

Reads ``/proc`` (Linux) once a second in a thread and, for a window of a measurement, gives
each process's share of a core and its CPU time per env step of the whole measurement. A
rate tells how fast; this tells whether the machine was full (the sum of the shares against
its cores) and which process a step's time went to.

    with CpuUse(roles={server.pid: ("pool front", "simulators")}) as cpu:
        started = time.monotonic(); ...; ended = time.monotonic()
        print(cpu.table(started, ended, env_steps_per_s))
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from types import TracebackType

TICKS_PER_S = os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class Process:
    pid: int
    parent: int
    command: str
    cpu_s: float
    """User and system time so far."""


def snapshot() -> dict[int, Process]:
    """Every process of this user that is readable now."""
    processes = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
            with open(f"/proc/{name}/cmdline", "rb") as cmdline:
                command = cmdline.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:  # gone meanwhile, or not ours to read
            continue
        cpu_s = (int(fields[11]) + int(fields[12])) / TICKS_PER_S
        processes[int(name)] = Process(int(name), int(fields[1]), command, cpu_s)
    return processes


class CpuUse:
    """Samples ``/proc`` every `interval_s` while open; `shares` reads a window of it."""

    def __init__(
        self, roles: dict[int, tuple[str, str]] | None = None, interval_s: float = 1.0
    ) -> None:
        """`roles`: for known pids, the name of the process and the name of its descendants."""
        self.roles = {os.getpid(): ("this process", "its child processes"), **(roles or {})}
        self.interval_s = interval_s
        self._samples: list[tuple[float, dict[int, Process]]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def __enter__(self) -> CpuUse:
        self._thread.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._samples.append((time.monotonic(), snapshot()))
            self._stop.wait(self.interval_s)

    def role(self, process: Process, processes: dict[int, Process]) -> str:
        """The role of `process`: its own, else its nearest named ancestor's descendants'."""
        if process.pid in self.roles:
            return self.roles[process.pid][0]
        parent, hops = processes.get(process.parent), 0
        while parent is not None and hops < 16:
            if parent.pid in self.roles:
                return self.roles[parent.pid][1]
            parent, hops = processes.get(parent.parent), hops + 1
        return "other"

    def shares(self, started: float, ended: float) -> dict[str, list[float]]:
        """Each role's processes' shares of a core between the samples nearest `started` and
        `ended`, busiest first (a role may have several: the simulators of a pool)."""
        if len(self._samples) < 2:
            return {}
        first = min(self._samples, key=lambda sample: abs(sample[0] - started))
        last = min(self._samples, key=lambda sample: abs(sample[0] - ended))
        seconds = last[0] - first[0]
        if seconds <= 0:
            return {}
        roles: dict[str, list[float]] = {}
        for pid, process in last[1].items():
            before = first[1].get(pid)
            share = (process.cpu_s - (before.cpu_s if before else 0.0)) / seconds
            role = self.role(process, last[1])
            if share >= 0.01 and role != "other":
                roles.setdefault(role, []).append(share)
        return {role: sorted(values, reverse=True) for role, values in roles.items()}

    def table(self, started: float, ended: float, env_steps_per_s: float) -> dict[str, object]:
        """`shares` and each role's CPU milliseconds per env step of the measurement."""
        shares = self.shares(started, ended)
        total = sum(sum(values) for values in shares.values())
        return {
            "cores_busy": total,
            "ms_per_env_step": 1e3 * total / env_steps_per_s,
            "roles": {
                role: {
                    "processes": len(values),
                    "cores": sum(values),
                    "ms_per_env_step": 1e3 * sum(values) / env_steps_per_s,
                }
                for role, values in sorted(shares.items(), key=lambda item: -sum(item[1]))
            },
        }


def describe(name: str, table: dict[str, object]) -> str:
    """`table` as a few lines for the screen."""
    lines = [f"   {name}: {table['cores_busy']:.2f} cores busy, "
             f"{table['ms_per_env_step']:.3f} ms of CPU per env step"]  # fmt: skip
    roles = table["roles"]
    assert isinstance(roles, dict)
    for role, use in roles.items():
        lines.append(f"     {role} ({use['processes']}): {use['cores']:.2f} cores, "
                     f"{use['ms_per_env_step']:.3f} ms/step")  # fmt: skip
    return "\n".join(lines)
