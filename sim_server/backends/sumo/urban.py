"""The built-in city: ``urban``, a signalised street grid with turns and crossing traffic.

Each reset draws the grid from its seed (junctions across and along, the block length, lanes per
direction, the speed limit, the signals' cycle) unless an option fixes it, and every light's
offset within its cycle, so that the green waves differ too. Short roads lead in and out at the
grid's edge. netgenerate builds each geometry once into the scenario cache (the grids are few);
the traffic and the ego's trip through the city are a map's (`maps`): seeded trips across the
grid, and a trip for the ego with the turns its route takes.

The lights are SUMO's static programmes for a four-arm junction: both directions of one street
green together, then the crossing street's; left turns give way to oncoming traffic (a
permissive green, ``g``), which `Road.stop_line` reports while foes with priority approach.
Source: SUMO docs, "netgenerate" (grid networks), "Simulation/Traffic Lights" (default
programmes).
"""

from __future__ import annotations

import random
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.options import Bounds, ParsedOptions, invalid_option
from sim_server.backends.sumo.maps import MapNetwork, map_options
from sim_server.backends.sumo.scenarios import ROAD_STEP_LENGTH, find_sumo_tool

GRID_COLUMNS = (3, 4, 5)
GRID_ROWS = (3, 4)
BLOCK_LENGTHS = (150.0, 200.0, 250.0)
STREET_LANES = (1, 2)
STREET_SPEEDS = (50 / 3.6, 60 / 3.6)
CYCLE_TIMES = (60.0, 90.0)
"""The grids the geometry is drawn from, uniformly and independently, per seed."""
ENTRY_LENGTH = 150.0
"""m of road leading into and out of the grid at each of its edge junctions."""
NETGENERATE_TIMEOUT_S = 120.0


@dataclass(frozen=True, slots=True)
class UrbanOptions(ParsedOptions):
    """The grid: 0 draws a value per seed, anything else fixes it."""

    columns: int = 0
    """Junctions across (3-5; 0: drawn)."""
    rows: int = 0
    """Junctions along (3 or 4; 0: drawn)."""
    block_length: float = 0.0
    """m between two junctions (0: drawn, 150, 200 or 250)."""
    lanes: int = 0
    """Lanes per direction (1 or 2; 0: drawn)."""
    street_speed: float = 0.0
    """The streets' speed limit (m/s; 0: drawn, 50 or 60 km/h)."""
    cycle_time: float = 0.0
    """s of one signal cycle (0: drawn, 60 or 90)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "columns": Bounds(0, 12, text="0 (drawn) or 2..12"),
        "rows": Bounds(0, 12, text="0 (drawn) or 2..12"),
        "block_length": Bounds(0.0, 2000.0, unit=" m"),
        "lanes": Bounds(0, 4, text="0 (drawn) or 1..4"),
        "street_speed": Bounds(0.0, 40.0, unit=" m/s"),
        "cycle_time": Bounds(0.0, 300.0, unit=" s"),
    }

    def check(self) -> None:
        for name in ("columns", "rows"):
            if getattr(self, name) == 1:
                raise invalid_option(f"option {name} must be 0 (drawn) or 2..12")
        if 0 < self.block_length < 50:
            raise invalid_option("option block_length must be 0 (drawn) or >= 50 m")
        if 0 < self.street_speed < 3:
            raise invalid_option("option street_speed must be 0 (drawn) or >= 3 m/s")
        if 0 < self.cycle_time < 20:
            raise invalid_option("option cycle_time must be 0 (drawn) or >= 20 s")


@dataclass(frozen=True, slots=True)
class Grid:
    """One drawn geometry."""

    columns: int
    rows: int
    block_length: float
    lanes: int
    speed: float
    cycle_time: float

    def netgenerate_args(self) -> list[str]:
        return [
            "--grid", "true",
            "--grid.x-number", str(self.columns),
            "--grid.y-number", str(self.rows),
            "--grid.x-length", f"{self.block_length:g}",
            "--grid.y-length", f"{self.block_length:g}",
            "--grid.attach-length", f"{ENTRY_LENGTH:g}",
            "--default.lanenumber", str(self.lanes),
            "--default.speed", f"{self.speed:.4f}",
            "--default-junction-type", "traffic_light",
            "--tls.default-type", "static",
            "--tls.cycle.time", f"{self.cycle_time:g}",
            "--no-turnarounds", "true",
        ]  # fmt: skip


def draw_grid(own: UrbanOptions, seed: int) -> Grid:
    """The geometry `seed` draws, with `own` options fixing what they set."""
    draw = random.Random(f"urban:{seed}")
    return Grid(
        columns=own.columns or draw.choice(GRID_COLUMNS),
        rows=own.rows or draw.choice(GRID_ROWS),
        block_length=own.block_length or draw.choice(BLOCK_LENGTHS),
        lanes=own.lanes or draw.choice(STREET_LANES),
        speed=own.street_speed or draw.choice(STREET_SPEEDS),
        cycle_time=own.cycle_time or draw.choice(CYCLE_TIMES),
    )


def build_grid(grid: Grid, cache_dir: Path) -> Path:
    """netgenerate's network of `grid`, built once into the cache; its path."""
    args = grid.netgenerate_args()
    name = "-".join(
        f"{v:g}" if isinstance(v, float) else str(v)
        for v in (
            grid.columns,
            grid.rows,
            grid.block_length,
            grid.lanes,
            grid.speed,
            grid.cycle_time,
        )
    )
    folder = cache_dir / "urban" / name
    net = folder / "urban.net.xml"
    if net.is_file():
        return net
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f"urban.net.xml.tmp{random.getrandbits(32)}"
    result = subprocess.run(
        [find_sumo_tool("netgenerate"), *args, "--output-file", str(tmp), "--no-warnings", "true"],
        capture_output=True,
        text=True,
        timeout=NETGENERATE_TIMEOUT_S,
        check=False,
    )
    if result.returncode != 0 or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"netgenerate failed ({result.returncode}): {result.stderr.strip()}")
    tmp.replace(net)
    return net


def shift_signals(api: Any, seed: int) -> None:
    """Give every light a seeded offset within its cycle: start it in the phase the offset
    falls in, with what is left of that phase."""
    draw = random.Random(f"offsets:{seed}")
    lights = api.trafficlight
    for light in sorted(lights.getIDList()):
        logic = lights.getAllProgramLogics(light)
        if not logic:
            continue
        durations = [phase.duration for phase in logic[0].phases]
        cycle = sum(durations)
        if cycle <= 0:
            continue
        offset = draw.uniform(0.0, cycle)
        for index, duration in enumerate(durations):
            if offset < duration:
                lights.setPhase(light, index)
                lights.setPhaseDuration(light, duration - offset)
                break
            offset -= duration


@dataclass(frozen=True)
class UrbanScenario:
    """The built-in city grid."""

    name: str
    description: str
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        own = UrbanOptions().as_options()
        options = map_options({**own, **self.defaults})
        return ScenarioInfo(self.name, self.description, options, ROAD_STEP_LENGTH)

    def network_for(
        self, options: Mapping[str, OptionValue], seed: int, cache_dir: Path
    ) -> MapNetwork:
        """The grid `seed` draws (built once)."""
        grid = draw_grid(UrbanOptions.parse(options), seed)
        return MapNetwork.of(build_grid(grid, cache_dir), cache_dir)

    def build(self, options: Mapping[str, OptionValue], cache_dir: Path) -> Path:
        """Build seed 0's grid (for an image's prebuilt cache); its network file."""
        return self.network_for(options, 0, cache_dir).net_file


URBAN = UrbanScenario(
    "urban",
    "city: a signalised street grid (3-5 x 3-4 junctions, 150-250 m blocks, 1-2 lanes, 50-60 "
    "km/h, 60-90 s cycles) with turns and crossing traffic; the ego's trip through it drawn "
    "per seed",
    defaults={
        "traffic": 60.0,
        "ego_route_min": 500.0,
        "ego_route_max": 1500.0,
        "max_episode_time": 600.0,
    },
)
