"""What does an ego-step cost with many egos in one SUMO simulation, against one simulation each?

For each number of egos N (1, 4, 16, 64 by default), on the ring, each ego driven by the client's
IDM (`agent_client.drivers.idm.IDMDriver`, one per ego), the same number of steps of:

* ``multi``    - one ``sim-server`` subprocess (SUMO in-process, libsumo) driving N egos in one
  simulation: a reset naming ``egos`` and one `MultiStep` per decision, over the bridge
  (``tcp://`` on loopback unless ``--transport direct``), this process as the client;
* ``inproc``   - the same simulation without the wire: `SumoBackend.step_many` called in this
  process (what the simulation and the observations cost alone);
* ``separate`` - N one-ego ``sim-server`` subprocesses, one simulation each, stepped in turn
  (one `Step` to each, one after the other: a round is one decision of every ego).

The ring has 10 m per vehicle (the density of Sugiyama's 22 cars on 230 m, near enough) and
two vehicles per ego, at least ``--vehicles`` (22): ``vehicles = max(22, 2 N)``,
``ring_length = 10 m x vehicles``, so the multi-ego ring is a mixed-autonomy ring with up to one
automated vehicle in two. Each separate simulation is the 22-vehicle ring with its one ego: the
same density and the smallest ring, so a separate ego costs what one ego on the standard ring
costs. Every episode warms up ``--warmup`` s (the humans' waves start forming), then runs
``--episode`` s; resets are not timed.

The figure is the wall time per ego-step: the time of the timed calls over (steps x egos). The
machine may be shared and noisy, so the variants of one N run interleaved, block by block
(``--block`` decisions each in turn, until each has run ``--steps``), and the ratios are given
overall and per round (median and the 10-90 % range). The N separate servers are started at
once (each waited for until it prints its readiness line) and stopped before the next N; with
``--separate-max`` the larger N are measured without them (they would not fit the machine).

    python benchmarks/egos.py                            # 1, 4, 16, 64 egos; writes nothing
    python benchmarks/egos.py --save                     # and benchmarks/results/egos.json

This is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.idm import IDMDriver
from agent_client.transport import Channel, connect
from protocol.messages import (
    Command,
    EgoObservation,
    Hello,
    MultiObservation,
    MultiStep,
    Observation,
    OptionValue,
    Reset,
    Step,
)
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.sumo.backend import SumoBackend

RESULTS = ROOT / "benchmarks" / "results" / "egos.json"
METRES_PER_VEHICLE = 10.0
READY_TIMEOUT_S = 300.0
"""Longest wait for a server's readiness line (many servers start at once on 2 cores)."""
REQUEST_TIMEOUT_S = 120.0
VARIANTS = ("multi", "inproc", "separate", "separate-parallel")


def ring_options(vehicles: int, args: argparse.Namespace) -> dict[str, OptionValue]:
    return {
        "vehicles": vehicles,
        "ring_length": METRES_PER_VEHICLE * vehicles,
        "warmup": args.warmup,
        "max_episode_time": args.episode,
    }


def single(multi: MultiObservation, ego: EgoObservation) -> Observation:
    """One ego's part as the `Observation` the one-ego IDM reads."""
    return Observation(multi.seq, multi.time, ego.ego, ego.neighbours, ego.events, ego.action)


class Timed:
    """A variant's timed calls: (ego-steps, ns) per block."""

    def __init__(self, variant: str, egos: int) -> None:
        self.variant = variant
        self.egos = egos
        self.blocks: list[tuple[int, int]] = []
        self.episodes = 0

    @property
    def ego_steps(self) -> int:
        return sum(n for n, _ in self.blocks)

    @property
    def us_per_ego_step(self) -> float:
        return sum(ns for _, ns in self.blocks) / 1e3 / self.ego_steps

    def to_dict(self) -> dict[str, Any]:
        per_decision = self.us_per_ego_step * self.egos
        return {
            "ego_steps": self.ego_steps,
            "episodes": self.episodes,
            "us_per_ego_step": round(self.us_per_ego_step, 2),
            "us_per_decision_of_all_egos": round(per_decision, 1),
            "ego_steps_per_s": round(1e6 / self.us_per_ego_step, 1),
        }


class Multi(Timed):
    """One simulation with N egos: `reset` and `step` are the wire's or the backend's."""

    def __init__(
        self,
        variant: str,
        egos: int,
        reset: Callable[[int], MultiObservation],
        step: Callable[[int, dict[str, tuple[float, int]]], MultiObservation],
        seed: int,
    ) -> None:
        super().__init__(variant, egos)
        self._reset, self._step, self._seed = reset, step, seed
        self._multi: MultiObservation | None = None
        self._drivers: dict[str, IDMDriver] = {}

    def run(self, decisions: int, record: bool = True) -> None:
        clock = time.perf_counter_ns
        ego_steps = spent = 0
        for _ in range(decisions):
            multi = self._multi
            if multi is None or multi.terminated or multi.truncated:
                multi = self._reset(self._seed + self.episodes)
                self.episodes += 1
            drivers = self._drivers
            commands = {
                e.id: drivers.setdefault(e.id, IDMDriver()).act(single(multi, e))
                for e in multi.egos
                if not e.reason
            }
            before = clock()
            self._multi = self._step(multi.seq + 1, commands)
            spent += clock() - before
            ego_steps += len(commands)
        if record:
            self.blocks.append((ego_steps, spent))


class Pool:
    """N one-ego simulations, each its own server, with each one's latest observation."""

    def __init__(self, channels: list[Channel], options: dict[str, OptionValue], seed: int):
        self.channels, self._options, self._seed = channels, options, seed
        self._obs: list[Observation | None] = [None] * len(channels)
        self._driver = IDMDriver()
        self.episodes = 0

    def decisions(self) -> list[Step]:
        """The next step of every simulation (a finished episode is reset first, untimed)."""
        steps = []
        for i, channel in enumerate(self.channels):
            obs = self._obs[i]
            if obs is None or obs.terminated or obs.truncated:
                seed = self._seed + 1000 * i + self.episodes
                reply = channel.request(Reset("ring", seed, self._options), REQUEST_TIMEOUT_S)
                assert isinstance(reply, Observation), reply
                obs = self._obs[i] = reply
                self.episodes += 1
            steps.append(Step(obs.seq + 1, *self._driver.act(obs)))
        return steps

    def observed(self, i: int, reply: object) -> None:
        assert isinstance(reply, Observation), reply
        self._obs[i] = reply


class Separate(Timed):
    """The pool's simulations stepped one after the other (``separate``: each request waits
    for its reply), or all at once (``separate-parallel``: every request sent, then every
    reply read, as `agent_client.envs.RemoteVectorEnv` steps its servers)."""

    def __init__(self, pool: Pool, parallel: bool) -> None:
        super().__init__("separate-parallel" if parallel else "separate", len(pool.channels))
        self._pool, self._parallel = pool, parallel

    def run(self, rounds: int, record: bool = True) -> None:
        clock = time.perf_counter_ns
        pool, channels = self._pool, self._pool.channels
        ego_steps = spent = 0
        for _ in range(rounds):
            steps = pool.decisions()
            before = clock()
            if self._parallel:
                for channel, step in zip(channels, steps, strict=True):
                    channel.send(step)
                replies = [channel.receive_checked() for channel in channels]
            else:
                replies = [
                    channel.request(step) for channel, step in zip(channels, steps, strict=True)
                ]
            spent += clock() - before
            for i, reply in enumerate(replies):
                pool.observed(i, reply)
            ego_steps += len(steps)
        if record:
            self.blocks.append((ego_steps, spent))

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "episodes": self._pool.episodes}


# --------------------------------------------------------------------------- servers


@contextlib.contextmanager
def servers(count: int, transport: str, cache_dir: Path) -> Iterator[list[tuple[Channel, int]]]:
    """`count` ``sim-server`` subprocesses started at once, each waited for until it prints its
    readiness line: a channel to each that has said hello, and its pid. All stopped on the way
    out."""
    bind = "direct://127.0.0.1:0" if transport == "direct" else "tcp://127.0.0.1:0"
    command = [
        sys.executable, "-m", "sim_server.cli", "--bind", bind, "--backend", "sumo",
        "--cache-dir", str(cache_dir), "--log-level", "WARNING", "--exit-with-parent",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    processes: list[subprocess.Popen[str]] = []
    with contextlib.ExitStack() as stack:
        try:
            logs = []
            for _ in range(count):
                log = stack.enter_context(tempfile.TemporaryFile(mode="w+"))
                process = subprocess.Popen(
                    command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log, text=True
                )
                processes.append(process)
                logs.append(log)
            channels = []
            for process, log in zip(processes, logs, strict=True):
                try:
                    address = wait_for_line(process, LISTENING, READY_TIMEOUT_S)
                except NotReady as exc:
                    log.seek(0)
                    raise RuntimeError(
                        f"sim-server did not become ready: {exc}\n{log.read()}"
                    ) from exc
                channel = stack.enter_context(connect(address, timeout_s=REQUEST_TIMEOUT_S))
                channel.request(Hello(PROTOCOL_VERSION, "benchmarks/egos.py"))
                channels.append((channel, process.pid))
            yield channels
        finally:
            stack.close()
            for process in processes:
                stop_process(process)


def memory_mb(pids: list[int]) -> dict[str, float]:
    """The memory of the processes `pids` together (MB, from /proc; 0 where unreadable):
    resident (``rss``) and proportional (``pss``: shared pages split among their users)."""
    totals = {"Rss:": 0, "Pss:": 0}
    for pid in pids:
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
                key = line.split(maxsplit=1)[0] if line else ""
                if key in totals:
                    totals[key] += int(line.split()[1])
    return {"rss": round(totals["Rss:"] / 1024, 1), "pss": round(totals["Pss:"] / 1024, 1)}


# --------------------------------------------------------------------------- measuring


def over_the_wire(channel: Channel, egos: int, options: dict[str, OptionValue]) -> tuple[
    Callable[[int], MultiObservation],
    Callable[[int, dict[str, tuple[float, int]]], MultiObservation],
]:  # fmt: skip
    def reset(seed: int) -> MultiObservation:
        reply = channel.request(Reset("ring", seed, {**options, "egos": egos}), REQUEST_TIMEOUT_S)
        assert isinstance(reply, MultiObservation), reply
        return reply

    def step(seq: int, commands: dict[str, tuple[float, int]]) -> MultiObservation:
        reply = channel.request(
            MultiStep(seq, tuple(Command(ego, a, lc) for ego, (a, lc) in commands.items()))
        )
        assert isinstance(reply, MultiObservation), reply
        return reply

    return reset, step


def measure(
    egos: int,
    args: argparse.Namespace,
    multi_channel: Channel,
    backend: SumoBackend,
    cache_dir: Path,
) -> dict[str, Any]:
    """Interleave the variants for `egos` egos; their figures and ratios."""
    vehicles = max(args.vehicles, 2 * egos)
    options = ring_options(vehicles, args)
    info = {s.name: s for s in backend.scenarios()}["ring"]
    local = {**info.options, **options, "egos": egos}
    runners: dict[str, Multi | Separate] = {
        "multi": Multi("multi", egos, *over_the_wire(multi_channel, egos, options), args.seed),
        "inproc": Multi(
            "inproc",
            egos,
            lambda seed: backend.reset_many("ring", seed, local, egos),
            backend.step_many,
            args.seed,
        ),
    }
    with contextlib.ExitStack() as stack:
        separate = egos <= args.separate_max
        memory: dict[str, float] = {}
        if separate:
            started = stack.enter_context(servers(egos, args.transport, cache_dir))
            channels = [channel for channel, _ in started]
            pool = Pool(channels, ring_options(args.vehicles, args), args.seed)
            runners["separate"] = Separate(pool, parallel=False)
            runners["separate-parallel"] = Separate(pool, parallel=True)
        for runner in runners.values():
            runner.run(min(20, args.block), record=False)  # imports, caches, the first episode
        if separate:
            memory = memory_mb([pid for _, pid in started])
        done = 0
        while done < args.steps:
            block = min(args.block, args.steps - done)
            for runner in runners.values():
                runner.run(block)
            done += block
    figures: dict[str, Any] = {
        "vehicles": vehicles,
        "ring_length": options["ring_length"],
        "separate_vehicles": args.vehicles if separate else None,
        "variants": {v: r.to_dict() for v, r in runners.items()},
        "ratios": ratios(runners),
    }
    if separate:
        figures["separate_servers_memory_mb"] = memory
    return figures


def ratios(runners: dict[str, Multi | Separate]) -> dict[str, dict[str, float]]:
    """How many times cheaper an ego-step is in `multi` / `inproc` than in the separate
    simulations, `multi` against `inproc` (the wire's share), and the separate ones in turn
    against all at once; overall and per round."""
    out = {}
    pairs = [
        ("separate", "multi"),
        ("separate-parallel", "multi"),
        ("separate", "inproc"),
        ("multi", "inproc"),
        ("separate", "separate-parallel"),
    ]
    for slow, fast in pairs:
        if slow not in runners or fast not in runners:
            continue
        a, b = runners[slow], runners[fast]
        per_round = sorted(
            (ta / na) / (tb / nb)
            for (na, ta), (nb, tb) in zip(a.blocks, b.blocks, strict=True)
        )  # fmt: skip
        deciles = (
            statistics.quantiles(per_round, n=10, method="inclusive")
            if len(per_round) > 1
            else per_round
        )
        out[f"{slow}_over_{fast}"] = {
            "overall": round(a.us_per_ego_step / b.us_per_ego_step, 3),
            "round_median": round(statistics.median(per_round), 3),
            "round_p10": round(deciles[0], 3),
            "round_p90": round(deciles[-1], 3),
        }
    return out


def _us(figures: dict[str, Any] | None) -> str:
    return f"{figures['us_per_ego_step']:.1f}" if figures else "not measured"


def _ratio(figures: dict[str, float] | None) -> str:
    if not figures:
        return "-"
    spread = f"{figures['round_median']:.2f}, {figures['round_p10']:.2f}-{figures['round_p90']:.2f}"
    return f"{figures['overall']:.2f}x ({spread})"


def table(results: dict[int, dict[str, Any]], transport: str) -> str:
    lines = [
        f"us per ego-step (wall time of the timed calls / ego-steps), ring at "
        f"{METRES_PER_VEHICLE:g} m per vehicle, {transport}://; ratios: overall (per round: "
        "median, 10-90 %)",
        "| egos | vehicles | one simulation, bridge | in-process | separate servers, in turn "
        "| all at once | in turn / one | all at once / one |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for egos, figures in results.items():
        variants, rates = figures["variants"], figures["ratios"]
        cells = [
            str(egos),
            str(figures["vehicles"]),
            *(_us(variants.get(v)) for v in ("multi", "inproc", "separate", "separate-parallel")),
            *(
                _ratio(rates.get(r))
                for r in ("separate_over_multi", "separate-parallel_over_multi")
            ),
        ]
        lines.append(f"| {' | '.join(cells)} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--egos", type=int, nargs="+", default=[1, 4, 16, 64])
    parser.add_argument("--steps", type=int, default=1000, help="timed decisions per variant")
    parser.add_argument("--block", type=int, default=100, help="decisions per variant and round")
    parser.add_argument("--vehicles", type=int, default=22, help="vehicles of the smallest ring")
    parser.add_argument("--warmup", type=float, default=60.0, help="s of warm-up per episode")
    parser.add_argument("--episode", type=float, default=300.0, help="max_episode_time (s)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the first episode")
    parser.add_argument(
        "--separate-max", type=int, default=64,
        help="measure the separate one-ego servers up to this many egos (default %(default)d)",
    )  # fmt: skip
    parser.add_argument("--transport", choices=("tcp", "direct"), default="tcp")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--save", action="store_true", help=f"write {RESULTS.relative_to(ROOT)}")
    args = parser.parse_args()

    report: dict[str, Any] = {
        "command": " ".join(["python", "benchmarks/egos.py", *sys.argv[1:]]),
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus, "
        f"Python {platform.python_version()}, load average {os.getloadavg()[0]:.2f} at start",
        "steps": args.steps,
        "block": args.block,
        "seed": args.seed,
        "transport": args.transport,
        "scenario": {
            "name": "ring",
            "metres_per_vehicle": METRES_PER_VEHICLE,
            "vehicles": f"max({args.vehicles}, 2 x egos)",
            "separate_vehicles": args.vehicles,
            "warmup": args.warmup,
            "max_episode_time": args.episode,
            "driver": "agent_client IDMDriver, one per ego",
        },
        "egos": {},
    }
    cache_root = Path(tempfile.mkdtemp(prefix="av-bridge-egos-"))
    results: dict[int, dict[str, Any]] = {}
    backend = SumoBackend(cache_dir=cache_root)
    try:
        with servers(1, args.transport, cache_root) as [(multi_channel, _)]:
            for egos in args.egos:
                results[egos] = measure(egos, args, multi_channel, backend, cache_root)
                report["egos"][str(egos)] = results[egos]
                if not args.json:
                    print(table({egos: results[egos]}, args.transport).splitlines()[-1], flush=True)
    finally:
        backend.close()
        shutil.rmtree(cache_root, ignore_errors=True)
    report["load_average_at_end"] = round(os.getloadavg()[0], 2)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(table(results, args.transport))
    if args.save:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(report, indent=2) + "\n")
        if not args.json:
            print(f"wrote {RESULTS.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
