"""SUMO behind the bridge: in-process through libsumo, or over TraCI to a sumo / sumo-gui process.

libsumo and TraCI have the same API, so one `SumoBackend` drives either: ``libsumo`` (the
default, one simulation per process, fastest) or a TraCI `Connection` to a ``sumo`` or
``sumo-gui`` process it starts from the eclipse-sumo wheel (or attaches to, on a port), to watch
the ego in the GUI or to share the simulation with another TraCI tool.

The ego is driven entirely by the client: speed mode 32 switches SUMO's safety checks off (the
agent can crash and must learn not to), lane-change mode 512 stops SUMO's own lane changes but
keeps its gap check on requested ones (a refused change is the paper's state G). Actions are
clipped to the announced bounds and to the road's speed limit here, because speed mode 32 would
obey anything. Collisions are real overlaps (``collision.mingap-factor 0``) and are checked before
arrival, so a crash at the end of the road is still a crash.

On the ``ring`` every vehicle is placed at reset: the ego is one of the human drivers during the
warm-up and is handed to the client (its type switched to the ego's) when the warm-up ends.

A reset that names ``egos`` (protocol 1.4, `reset_many` / `step_many`) drives several egos in
one simulation, ``ego.0``, ``ego.1``, ...: on the ring they are slots spread evenly round it, on
the roads they enter one after another after the warm-up and are handed over together once the
last has entered. Each is judged alone (`egos.EgoState`): an ego whose drive ends is reported
once and taken out, the others go on (docs/backends.md, "Many egos in one SUMO simulation").
A reset that names ``ego_share`` (protocol 1.5) makes that share of the traffic egos: on the
ring that many slots; on a road that share of the vehicles on it at the end of the warm-up, then
of the vehicles that enter, each joining at the end of the decision it entered in (`ShareDraw`).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import shutil
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

from protocol.errors import ErrorCode
from protocol.messages import (
    MAX_ROUTE_EDGES,
    ROAD_RANGE,
    AccelerationLimit,
    AppliedAction,
    Ego,
    EndReason,
    Events,
    LaneChangeRefusal,
    LeaderTrip,
    MultiObservation,
    Neighbour,
    Neighbours,
    Observation,
    OptionValue,
    Route,
    Safety,
    ScenarioInfo,
    SignalState,
    Traffic,
)
from sim_server.backends.base import Backend, Commands
from sim_server.backends.options import (
    MAX_EGOS,
    EpisodeOptions,
    ShareOptions,
    TrafficOptions,
    invalid_option,
)
from sim_server.backends.rules import (
    EndRule,
    LaneChangeUnderWay,
    ended,
    lane_change_refusal,
    limit_acceleration,
)
from sim_server.backends.sumo import ssm
from sim_server.backends.sumo.corridors import CORRIDORS, CorridorScenario
from sim_server.backends.sumo.egos import (
    QUIET,
    Drive,
    EgoState,
    ShareDraw,
    collision_partner,
    collision_partners,
    ego_ids,
    multi_observation,
)
from sim_server.backends.sumo.junctions import BLOCKING_LOOK, BLOCKING_TIME, JunctionFoes
from sim_server.backends.sumo.maps import (
    EPISODE_SLACK_S,
    TELEPORT_AFTER_S,
    MapNetwork,
    MapScenario,
    ego_route,
    episode_files,
)
from sim_server.backends.sumo.road import (
    FOE_DECELERATION,
    Foe,
    carried,
    road_ahead,
    stop_line,
    time_to_cover,
    too_close,
    yields_at,
)
from sim_server.backends.sumo.runtime import InProcess, OverTraci, check_display
from sim_server.backends.sumo.scenarios import (
    BUILTIN_SCENARIOS,
    EGO_ID,
    EGO_ROUTE,
    EGO_TYPE,
    HUMAN_TYPE,
    CustomScenario,
    MeasureOptions,
    RingOptions,
    RingScenario,
    RoadScenario,
    Scenario,
    ScenarioFiles,
    build_ring,
    build_road,
    default_cache_dir,
)
from sim_server.backends.sumo.signals import NO_SIGNAL, Programmes, next_signal, signal_line
from sim_server.backends.sumo.traffic import observe_traffic
from sim_server.backends.sumo.urban import URBAN, UrbanScenario, shift_signals
from sim_server.errors import BackendError

SPEED_MODE_NO_CHECKS = 32
LANE_CHANGE_MODE_REQUESTS_ONLY = 512
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""
CEILING_MIN_SPEED = 5.0
"""The slowest average speed (m/s) the leader-at-entry is waited for over its remaining route:
a leader that needs longer (held in a jam) leaves the ceiling unknown."""
CEILING_WALL_S = 2.0
"""Longest wall-clock time (s) spent waiting for the leader-at-entry: the episode's last reply
must come within any client's step deadline, whatever the network (a city of thousands of
vehicles simulates far slower than real time would allow an hour of it)."""
MAX_LIMIT_LANES = 20
"""Bound on the lanes ahead whose speed limits are looked at."""
YELLOW_STATES = frozenset("yY")
"""Link states of a yellow light."""
WAITING_POINT_DECELERATION = 4.0
"""m/s²: the hardest braking with which the ego stops at a waiting point it could not leave
the junction from before its light turns red."""
WAITING_POINT_OVERSHOOT = 0.5
"""m: an ego that stops no farther than this past its waiting point still stands at it."""
TURNED = frozenset("ru")
"""Link states of a light that has turned red against the vehicles still inside its junction
(yellow is not enough: the oncoming stream drives on through its own yellow, and a left turn
that went on its yellow met it on the Greenville export)."""
UNMEASURED = 1e6
"""m: a neighbour distance SUMO reports beyond this (its -DBL_MAX) was not measured."""
VEHICLE_LENGTH = 5.0
"""m: the ego's length where a gap is measured from positions (the built-in egos' length)."""
SAME_LINE = 1.0
"""m: a traffic light this close to the end of the ego's lane is the one at its next junction."""
FURTHER_LOOK = 20.0
"""m: a junction beyond the next is looked at within this, plus the ego's braking distance."""
FURTHER_DECELERATION = 3.0
"""m/s²: the braking that distance assumes."""
MAX_FURTHER_LINKS = 4
"""Bound on the junctions beyond the next looked at (and on a junction's lanes in a row)."""
PARTIAL_LOOK = 20.0
"""m before the end of its lane within which the ego looks for a vehicle that has entered the
junction with its rear still on the lane."""
ACROSS_LOOK = 50.0
"""m before a junction within which its far side is measured for the stop rule."""
INSERTION_WALL_S = 120.0
"""Longest wall-clock time (s) a reset waits for an ego to enter (beside the simulated
``insertion_timeout``): within the client's reset deadline on any network."""

# Command-line options forced on every scenario, also a user's own .sumocfg (a map's own take
# the time to teleport from `_forced_args`).
_FORCED_ARGS = [
    "--collision.action", "warn",
    "--collision.mingap-factor", "0",
    "--collision.check-junctions", "true",
    "--time-to-teleport", "-1",
    "--lanechange.duration", "2",
    "--no-step-log", "true",
    "--no-warnings", "true",
]  # fmt: skip

AnyScenario = Scenario | CorridorScenario | MapScenario | UrbanScenario
"""What a reset may load: a straight road, the ring, a corridor, the city, a user's own .sumocfg
or map."""
MapLike = MapScenario | UrbanScenario
"""Scenarios whose traffic and ego trip are drawn per seed over a network (`maps`)."""

_ABSENT = Neighbour(present=False, gap=0.0, lateral=0.0, speed=0.0)


@dataclass
class _Episode:
    """Book-keeping of the running episode (each ego's own in `egos`)."""

    dt: float
    substeps: int
    options: EpisodeOptions
    measures: MeasureOptions
    egos: list[EgoState]
    """The egos still driving, in the order they entered (one-ego episode: the one ego)."""
    route_length: float
    leader_id: str
    leader_depart: float
    many: bool = False
    """A multi-ego episode (`reset_many`): stepped by `step_many`, no ceiling, no SSM."""
    leader_arrival: float | None = None
    sumo_drives: bool = False
    one_way: bool = False
    """A built-in road: no lane beyond its edge's outer lanes (no opposite-direction lanes)."""
    curved: bool = False
    """The ring: one curved lane, where an offset across the ego's heading would be the
    curvature's; neighbours' `lateral` is 0 there."""
    done: bool = False
    lanes: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Lane id -> (its index, the lane count of its edge): neither changes during a run."""
    min_gaps: dict[str, float] = field(default_factory=dict)
    """Vehicle id -> its minGap (fixed by its type)."""
    ssm_log: Path | None = None
    """Where SUMO's SSM device logs the ego's conflicts (reset option ``ssm``)."""
    share: ShareDraw | None = None
    """Egos as a share of the traffic (``ego_share`` on a road): who joins next."""
    hand_over: float = math.nan
    """When the client took the first egos over (``ego_share``: the episode's time limit runs
    from it for those that join later too)."""
    signals: Programmes | None = None
    """The network's traffic lights' programmes, None on a network without lights (the next
    light and red lights passed are looked for only where there are lights)."""
    junction_foes: JunctionFoes | None = None
    """The foe lanes of the connections the egos took so far (made when first needed)."""

    ids: set[str] = field(init=False)
    """Every ego of the episode, running or not: none of them is `traffic`."""

    def __post_init__(self) -> None:
        self.ids = {e.id for e in self.egos}

    @property
    def ego(self) -> EgoState:
        """The one ego of a one-ego episode (the first still driving of a multi-ego one)."""
        return self.egos[0]


class SumoBackend(Backend):
    """Runs SUMO scenarios; reset reloads the running SUMO when it can.

    By default SUMO runs in this process through libsumo. With ``traci=True`` it runs in a
    ``sumo`` process (``sumo-gui`` with ``gui=True``) driven over TraCI, or, with `traci_port`,
    in a SUMO another tool started with ``--remote-port``. Same scenarios, same observations.
    """

    name = "sumo"

    def __init__(
        self,
        cache_dir: Path | None = None,
        custom: tuple[CustomScenario | MapScenario, ...] = (),
        restart_every: int = 50,
        *,
        traci: bool = False,
        gui: bool = False,
        traci_port: int | None = None,
        traci_host: str = "localhost",
        sumo_binary: str | None = None,
        view: Any = None,
    ) -> None:
        if not traci and (gui or traci_port is not None or sumo_binary is not None):
            raise ValueError("gui, traci_port and sumo_binary need traci=True")
        if view is not None and not gui:
            raise ValueError("a GUI view needs gui=True")
        if gui and traci_port is not None:
            raise ValueError("gui starts its own sumo-gui: it cannot attach to a port")
        if gui:
            check_display()
        self._cache_dir = cache_dir or default_cache_dir()
        self._scenarios: dict[str, AnyScenario] = {
            **BUILTIN_SCENARIOS,
            **CORRIDORS,
            URBAN.name: URBAN,
        }
        for scenario in custom:
            self._scenarios[scenario.name] = scenario
        over_traci = OverTraci(gui, traci_port, traci_host, sumo_binary, view) if traci else None
        self._sumo: InProcess | OverTraci = over_traci or InProcess()
        self.name = self._sumo.name
        self._errors = self._sumo.errors
        self._api: Any = None
        self._restart_every = restart_every
        self._loads = 0
        self._running = False
        self._episode: _Episode | None = None
        self._absent = replace(_ABSENT, gap=self.sensor_range)
        self._logs: Path | None = None
        """A temporary folder of SSM logs, made when first needed."""
        self._log_numbers = itertools.count()
        self._lane_lengths: dict[str, float] = {}
        self._episode_files: Path | None = None
        """A temporary folder of the running map episode's files, made when first needed."""
        self._network: MapNetwork | None = None
        """The network of the running episode where the ego's trip is drawn over it."""
        self._networks: dict[Path, MapNetwork] = {}
        """Networks read for random ego trips on a user's .sumocfg, by file."""
        if over_traci is not None and traci_port is not None:
            try:
                self._api = over_traci.attach()
            except self._errors as exc:
                where = f"{traci_host}:{traci_port}"
                raise ValueError(f"cannot attach to SUMO at {where}: {exc}") from exc
            self._running = True
        self._version = self._sumo.version()

    @property
    def version(self) -> str:
        return self._version

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(s.info() for s in self._scenarios.values())

    # ----------------------------------------------------------------------- reset

    max_egos = MAX_EGOS

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        (first,) = self._start(scenario, seed, options, (EGO_ID,), many=False)
        return first

    def reset_many(
        self, scenario: str, seed: int, options: dict[str, OptionValue], egos: int
    ) -> MultiObservation:
        """Start an episode with `egos` egos ``ego.0``, ``ego.1``, ... (seq 0): on the ring,
        slots spread evenly round it; on the roads, entered one after another after the warm-up
        (the reset returns once all have entered, each within ``insertion_timeout``)."""
        if not 1 <= egos <= self.max_egos:
            raise invalid_option(f"option egos must be within 1..{self.max_egos}, got {egos}")
        share = ShareOptions.parse(options).ego_share
        chosen = self._scenarios[scenario]
        if share and isinstance(chosen, RingScenario):  # that many of the ring's slots
            egos = max(1, math.floor(share * RingOptions.parse(options).vehicles + 0.5))
            share = 0.0
        ids = ego_ids(egos) if not share else ()
        first = self._start(scenario, seed, options, ids, many=True, share=share)
        episode = self._episode
        assert episode is not None
        try:
            traffic = self._traffic(episode)
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during reset: {exc}"
            ) from exc
        reported = zip([ego.id for ego in episode.egos], first, strict=True)
        return multi_observation(0, first[0].time, reported, False, "", traffic)

    def _start(
        self,
        scenario: str,
        seed: int,
        options: dict[str, OptionValue],
        ids: tuple[str, ...],
        *,
        many: bool,
        share: float = 0.0,
    ) -> list[Observation]:
        """Load the scenario and hand the egos `ids` over (a road's `share`: that share of its
        traffic instead); their seq-0 observations (`many`: without traffic, which the
        multi-ego reply carries once)."""
        chosen = self._scenarios[scenario]
        episode_options = EpisodeOptions.parse(options)
        on_road = isinstance(chosen, RoadScenario | CorridorScenario)
        traffic = TrafficOptions.parse(options) if on_road else None
        layout = RingOptions.parse(options) if isinstance(chosen, RingScenario) else None
        measures = MeasureOptions.parse(options)
        slots = layout.ego_slots(len(ids)) if layout is not None else ()
        if many and measures.ssm:
            raise invalid_option(
                "option ssm is not offered with egos: a multi_observation carries no safety"
            )
        self._episode = None
        try:
            files = self._files(chosen, options, seed, slots)
            log = self._new_ssm_log() if measures.ssm else None
            device = ssm.device_args(EGO_ID, log) if log is not None else []
            forced = _forced_args(TELEPORT_AFTER_S if isinstance(chosen, MapLike) else -1)
            self._load(["-c", str(files.config), "--seed", str(seed), *forced, *device])
            self._lane_lengths = {}  # another network, perhaps
            self._drop_old_logs(keep=log)
            if self._network is not None:  # the ego's trip, drawn from the seed
                if EGO_TYPE not in self._api.vehicletype.getIDList():
                    self._define_ego_type()  # a user's .sumocfg: the route is the ego type's
                edges = ego_route(self._api, self._network, options, seed)
                self._api.route.add(files.ego_route, edges)
            if isinstance(chosen, UrbanScenario):
                shift_signals(self._api, seed)
            if layout is not None:
                first = self._place_egos(layout, slots, ids, episode_options, measures, many)
            elif share:
                draw = ShareDraw(share, seed)
                first = self._hand_over_share(draw, episode_options, measures, traffic is not None)
            else:
                first = self._insert_egos(
                    files, ids, episode_options, measures, one_way=traffic is not None, many=many
                )
            assert self._episode is not None
            self._episode.ssm_log = log
            self._sumo.ego_ready(self._api, self._episode.ego.id)
            return first
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during reset: {exc}"
            ) from exc

    def _files(
        self,
        scenario: AnyScenario,
        options: dict[str, OptionValue],
        seed: int,
        ego_slots: tuple[int, ...] = (0,),
    ) -> ScenarioFiles:
        """The scenario's files: a built-in one's built from its `options` (a corridor's
        geometry drawn from the `seed`; the ring's humans leave `ego_slots` free), and the
        egos' route (the ring's egos are placed by `_place_egos` instead)."""
        self._network = None
        if isinstance(scenario, CustomScenario):
            if not scenario.random_route:
                return ScenarioFiles(scenario.sumocfg, scenario.ego_route)
            self._network = self._user_network(scenario)
            return ScenarioFiles(scenario.sumocfg, f"{EGO_ROUTE}.{seed}", "best")
        cache = self._cache_dir
        try:
            if isinstance(scenario, MapLike):
                self._network = network = scenario.network_for(options, seed, cache)
                episode = EpisodeOptions.parse(options)
                horizon = (
                    episode.warmup + episode.insertion_timeout + episode.max_episode_time
                    + EPISODE_SLACK_S
                )  # fmt: skip
                return episode_files(network, options, seed, horizon, self._map_folder())
            if isinstance(scenario, RingScenario):
                return ScenarioFiles(build_ring(scenario, options, cache, ego_slots), "")
            if isinstance(scenario, CorridorScenario):
                return scenario.files(options, seed, cache)
            return ScenarioFiles(build_road(scenario, options, cache), EGO_ROUTE)
        except (OSError, RuntimeError, ValueError) as exc:
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"could not build scenario {scenario.name}: {exc}"
            ) from exc

    def _user_network(self, scenario: CustomScenario) -> MapNetwork:
        """The network of a user's .sumocfg, read once, for random ego trips over it."""
        net_file = scenario.net_file()
        known = self._networks.get(net_file)
        if known is None:
            try:
                known = self._networks[net_file] = MapNetwork.of(net_file, self._cache_dir)
            except (OSError, ValueError, ElementTree.ParseError) as exc:
                raise BackendError(
                    ErrorCode.SIMULATOR_ERROR, f"could not read the network {net_file}: {exc}"
                ) from exc
        return known

    def _map_folder(self) -> Path:
        """Where a map's episode files go (its route file and .sumocfg), made once."""
        if self._episode_files is None:
            self._episode_files = Path(tempfile.mkdtemp(prefix="av-bridge-map-"))
        return self._episode_files

    def _load(self, args: list[str]) -> None:
        if self._running and (self._loads < self._restart_every or not self._sumo.restarts):
            self._sumo.load(self._api, args)
            self._loads += 1
            return
        if self._running:
            self._sumo.close(self._api)
            self._running = False
        self._api = self._sumo.start(args)
        self._running = True
        self._loads = 0

    def _insert_egos(
        self,
        files: ScenarioFiles,
        ids: tuple[str, ...],
        options: EpisodeOptions,
        measures: MeasureOptions,
        *,
        one_way: bool,
        many: bool,
    ) -> list[Observation]:
        """Warm up, insert the egos one after another at the start of their route (each as soon
        as SUMO can, in the lane `files` says) and observe them (seq 0). An ego waiting for the
        next to enter is driven by SUMO with its safety checks on; they all go off at the
        hand-over, when the last has entered. The leader-at-entry (the ceiling) is the one ego's
        only."""
        api = self._api
        dt = api.simulation.getDeltaT()
        substeps = options.steps_per_decision(dt)
        api.simulationStep(api.simulation.getTime() + options.warmup)
        offsets = []
        for k, ego_id in enumerate(ids):
            last = k == len(ids) - 1
            self._add_ego(ego_id, files, options.simulator_drives, checks_off=last)
            self._wait_for_entry(ego_id, options.insertion_timeout, ids[:k])
            offsets.append(api.vehicle.getLanePosition(ego_id))
        if not options.simulator_drives:
            for ego_id in ids[:-1]:
                api.vehicle.setSpeedMode(ego_id, SPEED_MODE_NO_CHECKS)
        first = ids[0]
        edges = api.vehicle.getRoute(first)
        route_length = sum(api.lane.getLength(f"{edge}_0") for edge in edges)
        leader_id = "" if many else self._leader_at_entry(first, edges, route_length)
        entry_time = api.simulation.getTime()
        egos = [
            EgoState(ego_id, EndRule(options, entry_time), offset, api.vehicle.getMinGap(ego_id))
            for ego_id, offset in zip(ids, offsets, strict=True)
        ]
        self._episode = episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            measures=measures,
            egos=egos,
            route_length=route_length,
            leader_id=leader_id,
            leader_depart=api.vehicle.getDeparture(leader_id) if leader_id else math.nan,
            many=many,
            sumo_drives=options.simulator_drives,
            one_way=one_way,
            signals=self._programmes(),
        )
        if not many:
            egos[0].route = tuple(edges)
        action = AppliedAction(0.0, 0, 0.0, 0)
        observed = [self._observe(episode, ego, 0, Events(), action, not many) for ego in egos]
        if not many:
            observed[0] = replace(observed[0], route=self._route(episode, egos[0], arrived=False))
        return observed

    def _programmes(self) -> Programmes | None:
        """The loaded network's traffic lights (their programmes read as needed), or None
        where it has none."""
        api = self._api
        return Programmes(api) if api.trafficlight.getIDCount() > 0 else None

    def _route(self, episode: _Episode, ego: EgoState, *, arrived: bool) -> Route | None:
        """The ego's route as the first and the last observation report it (None on the ring,
        whose route goes round it lap after lap)."""
        if not ego.route:
            return None
        driven = len(ego.route) if arrived else ego.route_index + 1
        return Route(ego.route[:MAX_ROUTE_EDGES], episode.route_length, driven)

    def _leader_at_entry(self, ego_id: str, route: Any, route_length: float) -> str:
        """The vehicle directly ahead of the ego at its entry, if it drives the ego's whole
        route: only then does its trip bound the ego's (a leader that turns off, or came from
        elsewhere, bounds nothing); "" otherwise."""
        vehicle = self._api.vehicle
        leader = (vehicle.getLeader(ego_id, route_length) or ("", 0.0))[0]
        return leader if leader and tuple(vehicle.getRoute(leader)) == tuple(route) else ""

    def _place_egos(
        self,
        layout: RingOptions,
        slots: tuple[int, ...],
        ids: tuple[str, ...],
        options: EpisodeOptions,
        measures: MeasureOptions,
        many: bool,
    ) -> list[Observation]:
        """The ring: the egos join the humans in their `slots`, drive as humans through the
        warm-up, and are handed over at its end (seq 0)."""
        api = self._api
        dt = api.simulation.getDeltaT()
        substeps = options.steps_per_decision(dt)
        for ego_id, slot in zip(ids, slots, strict=True):
            route, position = layout.slot(slot)
            api.vehicle.add(
                ego_id, route, typeID=HUMAN_TYPE, depart="now",
                departLane="0", departPos=f"{position:.3f}", departSpeed="0",
            )  # fmt: skip
        api.simulationStep()  # everyone enters in this first step, or the ring is refused
        self._check_ring_entry(layout.vehicles, ids)
        api.simulationStep(max(options.warmup, api.simulation.getTime()))
        if not options.simulator_drives:
            for ego_id in ids:
                api.vehicle.setType(ego_id, EGO_TYPE)
                api.vehicle.setSpeedMode(ego_id, SPEED_MODE_NO_CHECKS)
                api.vehicle.setLaneChangeMode(ego_id, LANE_CHANGE_MODE_REQUESTS_ONLY)
        entry_time = api.simulation.getTime()
        egos = [
            EgoState(
                ego_id,
                EndRule(options, entry_time),
                layout.ring_position(slot),
                api.vehicle.getMinGap(ego_id),
            )
            for ego_id, slot in zip(ids, slots, strict=True)
        ]
        self._episode = episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            measures=measures,
            egos=egos,
            route_length=layout.laps() * layout.ring_length,
            leader_id="",  # nobody arrives on a ring: no leader-at-entry trip (ceiling nil)
            leader_depart=math.nan,
            many=many,
            sumo_drives=options.simulator_drives,
            one_way=True,
            curved=True,
        )
        action = AppliedAction(0.0, 0, 0.0, 0)
        return [self._observe(episode, ego, 0, Events(), action, not many) for ego in egos]

    def _hand_over_share(
        self, draw: ShareDraw, options: EpisodeOptions, measures: MeasureOptions, one_way: bool
    ) -> list[Observation]:
        """A road's egos as a share of its traffic: warm up, take `draw`'s share of the vehicles
        on the road over (in the order they entered), observe them (seq 0); the vehicles that
        enter later join in `_step_many`."""
        api = self._api
        dt = api.simulation.getDeltaT()
        substeps = options.steps_per_decision(dt)
        api.simulationStep(api.simulation.getTime() + options.warmup)
        on_road = sorted(api.vehicle.getIDList(), key=lambda v: (api.vehicle.getDeparture(v), v))
        if not on_road:
            raise BackendError(
                ErrorCode.INSERTION_FAILED,
                f"no vehicle on the road after the {options.warmup:g} s warm-up to hand over: "
                "ask for a longer warmup or a higher flow",
            )
        if not options.simulator_drives and EGO_TYPE not in api.vehicletype.getIDList():
            self._define_ego_type()
        self._episode = episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            measures=measures,
            egos=[],
            route_length=0.0,
            leader_id="",
            leader_depart=math.nan,
            many=True,
            sumo_drives=options.simulator_drives,
            one_way=one_way,
            share=draw,
            hand_over=api.simulation.getTime(),
            signals=self._programmes(),
        )
        action = AppliedAction(0.0, 0, 0.0, 0)
        return [
            self._observe(episode, self._take_over(episode, vehicle), 0, Events(), action, False)
            for vehicle in draw.at_hand_over(on_road)
        ]

    def _take_over(self, episode: _Episode, vehicle: str) -> EgoState:
        """Make a human driver on the road an ego of the running episode (the client's, unless
        the simulator drives): the ego's type, SUMO's checks and own lane changes off. It
        shares the episode's time limit."""
        api = self._api
        if not episode.sumo_drives:
            api.vehicle.setType(vehicle, EGO_TYPE)
            api.vehicle.setSpeedFactor(vehicle, 1.0)
            api.vehicle.setSpeedMode(vehicle, SPEED_MODE_NO_CHECKS)
            api.vehicle.setLaneChangeMode(vehicle, LANE_CHANGE_MODE_REQUESTS_ONLY)
        offset = api.vehicle.getLanePosition(vehicle) - api.vehicle.getDistance(vehicle)
        ego = EgoState(
            vehicle, EndRule(episode.options, episode.hand_over), offset,
            api.vehicle.getMinGap(vehicle),
        )  # fmt: skip
        episode.egos.append(ego)
        episode.ids.add(vehicle)
        if episode.route_length == 0.0:
            edges = api.vehicle.getRoute(vehicle)
            episode.route_length = sum(api.lane.getLength(f"{edge}_0") for edge in edges)
        return ego

    def _check_ring_entry(self, vehicles: int, ids: tuple[str, ...]) -> None:
        """Every vehicle of the ring entered in the first step (placed, so they must)."""
        entered = self._api.simulation.getDepartedIDList()
        if len(entered) != vehicles or not set(entered).issuperset(ids):
            raise BackendError(
                ErrorCode.INSERTION_FAILED,
                f"only {len(entered)} of the ring's {vehicles} vehicles could be placed",
            )

    def _add_ego(
        self, ego_id: str, files: ScenarioFiles, sumo_drives: bool, checks_off: bool
    ) -> None:
        """Ask SUMO to insert an ego now: the client's (SUMO's own lane changes off, its safety
        checks too if `checks_off`, else at the hand-over) or a human."""
        api = self._api
        types = api.vehicletype.getIDList()
        if sumo_drives:  # a human driver of the scenario, driven by SUMO, observed by the client
            type_id = HUMAN_TYPE if HUMAN_TYPE in types else "DEFAULT_VEHTYPE"
        else:
            type_id = EGO_TYPE
            if EGO_TYPE not in types:
                self._define_ego_type()
        api.vehicle.add(
            ego_id, files.ego_route, typeID=type_id, depart="now",
            departLane=files.depart_lane, departPos="base", departSpeed="max",
        )  # fmt: skip
        if not sumo_drives:
            if checks_off:
                api.vehicle.setSpeedMode(ego_id, SPEED_MODE_NO_CHECKS)
            api.vehicle.setLaneChangeMode(ego_id, LANE_CHANGE_MODE_REQUESTS_ONLY)

    def _wait_for_entry(self, ego_id: str, timeout: float, entered: tuple[str, ...]) -> None:
        """Step until `ego_id` has entered; give up after `timeout` s of simulation, or when an
        ego that `entered` before it reaches the end of the road meanwhile."""
        api = self._api
        deadline = api.simulation.getTime() + timeout
        wall_deadline = time.monotonic() + INSERTION_WALL_S
        while ego_id not in api.simulation.getDepartedIDList():
            late = time.monotonic() >= wall_deadline
            if api.simulation.getTime() >= deadline or late:
                api.vehicle.remove(ego_id)
                who = "the ego" if ego_id == EGO_ID else ego_id
                waited = f"{INSERTION_WALL_S:g} s of wall-clock time" if late else f"{timeout} s"
                raise BackendError(
                    ErrorCode.INSERTION_FAILED,
                    f"{who} could not enter within {waited} "
                    "(road too full at the entry); try a lower flow or another seed",
                )
            api.simulationStep()
            if entered:
                arrived = api.simulation.getArrivedIDList()
                gone = next((e for e in entered if e in arrived), None)
                if gone is not None:
                    api.vehicle.remove(ego_id)
                    raise BackendError(
                        ErrorCode.INSERTION_FAILED,
                        f"{gone} reached the end of the road before {ego_id} could enter: ask "
                        "for fewer egos, a lower flow, or use the ring",
                    )

    def _define_ego_type(self) -> None:
        """A user's .sumocfg has no ego type: derive one like the built-in scenarios'."""
        api = self._api
        api.vehicletype.copy("DEFAULT_VEHTYPE", EGO_TYPE)
        api.vehicletype.setImperfection(EGO_TYPE, 0.0)
        api.vehicletype.setSpeedFactor(EGO_TYPE, 1.0)
        api.vehicletype.setSpeedDeviation(EGO_TYPE, 0.0)
        api.vehicletype.setAccel(EGO_TYPE, 3.0)
        api.vehicletype.setDecel(EGO_TYPE, 6.0)
        api.vehicletype.setEmergencyDecel(EGO_TYPE, 9.0)

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        if episode.many:
            raise BackendError(
                ErrorCode.OUT_OF_ORDER, "step in an episode of several egos: send multi_step"
            )
        try:
            return self._step(episode, seq, acceleration, lane_change)
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during step: {exc}"
            ) from exc

    def _step(self, episode: _Episode, seq: int, request: float, lane_change: int) -> Observation:
        ego = episode.ego
        drive = self._decide(episode, ego, request, lane_change)
        self._drive(episode, drive)
        self._sumo.stepped(self._api, ego.id)
        action, events = drive.outcome()
        obs = self._judge(episode, ego, seq, events, action)
        return self._finish(episode, obs) if obs.reason else obs

    def _decide(self, episode: _Episode, ego: EgoState, request: float, lane_change: int) -> Drive:
        """One ego's command, its lane change judged (and started) before the simulation
        steps."""
        refused = self._lane_change_refusal(episode, ego, lane_change) if lane_change else ""
        started = bool(lane_change) and not refused
        drive = Drive(ego, request, lane_change, refused, started)
        if started:
            self._start_lane_change(episode, ego, lane_change)
        elif refused == LaneChangeRefusal.GAP_TOO_SMALL and _route_needs(ego, lane_change):
            drive.signalled_from = self._signal_lane_change(episode, ego, lane_change)
        return drive

    def _lane_change_refusal(self, episode: _Episode, ego: EgoState, direction: int) -> str:
        could_change = self._api.vehicle.couldChangeLane
        return lane_change_refusal(
            direction,
            simulator_drives=episode.sumo_drives,
            under_way=ego.lane_change,
            ego_lane=lambda: self._lane(episode, ego.id),
            # SUMO's own gap check of a requested change (lane-change mode 512 keeps it)
            gap_ok=lambda side: bool(could_change(ego.id, side)),
        )

    def _start_lane_change(self, episode: _Episode, ego: EgoState, direction: int) -> None:
        """Ask SUMO for the change: the request stands for 2 s, the manoeuvre takes 2 s
        (``--lanechange.duration``)."""
        target = self._lane(episode, ego.id)[0] + direction
        self._api.vehicle.changeLane(ego.id, target, 2.0)
        now = self._api.simulation.getTime()
        ego.lane_change = LaneChangeUnderWay(target, direction, now)

    def _signal_lane_change(
        self, episode: _Episode, ego: EgoState, direction: int
    ) -> tuple[str, int]:
        """Keep a change the route needs requested over the decision although its gap is too
        small now; returns the ego's road and lane. SUMO's drivers then make room for it as
        they do for each other's strategic changes (LC2013 asks the blocking leader and
        follower in the target lane to adapt their speed to a requested change), and SUMO
        starts it within the decision if its own gap check passes (lane-change mode 512):
        `_signalled_start` sees that. The request ends before the next decision's first step."""
        vehicle = self._api.vehicle
        lane = self._lane(episode, ego.id)[0]
        vehicle.changeLane(ego.id, lane + direction, (episode.substeps - 0.5) * episode.dt)
        return vehicle.getRoadID(ego.id), lane

    def _signalled_start(self, drive: Drive, source: tuple[str, int]) -> None:
        """Turn a signalled change (`_signal_lane_change`) that SUMO started in the last
        simulation step into the lane change under way, reported as started."""
        vehicle = self._api.vehicle
        ego = drive.ego
        road, lane = source
        target = lane + drive.lane_change
        if vehicle.getRoadID(ego.id) != road:  # a lane index means another lane there: drop it
            vehicle.changeLane(ego.id, vehicle.getLaneIndex(ego.id), 0.0)
            drive.signalled_from = None
            return
        moved = vehicle.getLaneIndex(ego.id) == target
        if not moved and abs(vehicle.getLateralLanePosition(ego.id)) <= 1e-6:
            return
        now = self._api.simulation.getTime()
        ego.lane_change = LaneChangeUnderWay(target, drive.lane_change, now)
        drive.signalled_from = None
        drive.started, drive.refused = True, ""

    def _drive(self, episode: _Episode, drive: Drive) -> None:
        """Run the decision's simulation steps; stop early at a collision or the ego's arrival."""
        api = self._api
        simulation = api.simulation
        ego = drive.ego
        ego_id = ego.id
        signals = episode.signals is not None
        for _ in range(episode.substeps):
            applied, why = self._substep(episode, ego_id, drive.request)
            drive.applied(applied, why)
            drive.collision_with, drive.collision_type = collision_partner(
                simulation.getCollisions(), ego_id
            )
            arrived = simulation.getArrivedIDList()
            if episode.leader_arrival is None and episode.leader_id in arrived:
                episode.leader_arrival = simulation.getTime()
            drive.teleported = drive.teleported or ego_id in simulation.getStartingTeleportIDList()
            if drive.collision_with:
                break
            if ego_id in arrived:
                drive.end_of_road = True
                break
            if signals and ego.red_lights.passed_red(api, ego_id):
                drive.red_light = True
            self._lane_change_steps(drive)

    def _substep(self, episode: _Episode, ego_id: str, request: float) -> tuple[float, str]:
        """One simulation step: the applied acceleration and what limited it ("" nothing)."""
        api = self._api
        if episode.sumo_drives:
            api.simulationStep()
            gone = ego_id in api.simulation.getArrivedIDList()
            return 0.0 if gone else api.vehicle.getAcceleration(ego_id), AccelerationLimit.SIMULATOR
        applied, why = self._apply(episode, ego_id, request)
        api.simulationStep()
        return applied, why

    def _apply(self, episode: _Episode, ego_id: str, request: float) -> tuple[float, str]:
        """Set the ego's acceleration for the next simulation step, limited by the rules."""
        vehicle = self._api.vehicle
        applied, why = limit_acceleration(
            request,
            vehicle.getSpeed(ego_id),
            vehicle.getAllowedSpeed(ego_id),
            self.action_schema.acceleration_min,
            self.action_schema.acceleration_max,
            episode.dt,
        )
        vehicle.setAcceleration(ego_id, applied, episode.dt)
        return applied, why

    def _lane_change_progress(self, ego: EgoState, change: LaneChangeUnderWay) -> tuple[bool, bool]:
        """(completed, aborted) of the lane change under way; either ends it."""
        vehicle = self._api.vehicle
        if (
            vehicle.getLaneIndex(ego.id) == change.target
            and abs(vehicle.getLateralLanePosition(ego.id)) < 1e-6
        ):
            ego.lane_change = None
            return True, False
        if change.expired(self._api.simulation.getTime()):
            ego.lane_change = None
            return False, True
        return False, False

    def _judge(
        self,
        episode: _Episode,
        ego: EgoState,
        seq: int,
        events: Events,
        action: AppliedAction,
        traffic: bool = True,
    ) -> Observation:
        """The ego's observation after a step, the last one of its drive if a rule ends it."""
        if events.end_of_road:
            arrival = self._arrival_observation(episode, ego, seq, events, action, traffic)
            return ended(arrival, EndReason.END_OF_ROAD)
        obs = (
            None
            if events.teleported
            else self._observe_if_present(episode, ego, seq, events, action, traffic)
        )
        if obs is None:  # gone without arriving
            lost = self._arrival_observation(episode, ego, seq, events, action, traffic)
            return ended(lost, EndReason.EGO_LOST)
        reason = ego.end.check(obs, ego.give_way, ego.across)
        return obs if reason is None else ended(obs, reason)

    def _observe_if_present(
        self,
        episode: _Episode,
        ego: EgoState,
        seq: int,
        events: Events,
        action: AppliedAction,
        traffic: bool,
    ) -> Observation | None:
        """The observation, or None if the ego has left without arriving (its state cannot be
        read)."""
        try:
            return self._observe(episode, ego, seq, events, action, traffic)
        except self._errors:
            if ego.id in self._api.vehicle.getIDList():
                raise
            return None

    def _finish(self, episode: _Episode, obs: Observation) -> Observation:
        """End the one-ego episode: take the ego out and report the leader-at-entry's trip."""
        api = self._api
        episode.done = True
        ego_id = episode.ego.id
        if ego_id in api.vehicle.getIDList():
            api.vehicle.remove(ego_id)
        route = self._route(episode, episode.ego, arrived=obs.events.end_of_road)
        if route is not None:
            obs = replace(obs, route=route)
        if episode.options.report_ceiling:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        if episode.ssm_log is not None:
            obs = replace(obs, safety=self._conflicts(episode, episode.ssm_log))
        return obs

    # ----------------------------------------------------------------------- many egos

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        """Apply every running ego's command in the same simulation steps; an ego whose drive
        ends is reported once (at the simulation step where it ended) and taken out."""
        episode = self._episode
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        if not episode.many:
            return super().step_many(seq, commands)
        try:
            if len(commands) != len(episode.egos):
                raise KeyError
            requests = [commands[ego.id] for ego in episode.egos]
        except KeyError:
            running = ", ".join(ego.id for ego in episode.egos)
            raise BackendError(
                ErrorCode.INVALID_MESSAGE,
                f"multi_step {seq}: commands for {', '.join(sorted(commands))}, running: {running}",
            ) from None
        try:
            return self._step_many(episode, seq, requests)
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during step: {exc}"
            ) from exc

    def _step_many(
        self, episode: _Episode, seq: int, requests: list[tuple[float, int]]
    ) -> MultiObservation:
        """`requests`: each running ego's (acceleration, lane change), in their order."""
        decide = self._decide
        drives = [
            decide(episode, ego, acceleration, lane_change)
            for ego, (acceleration, lane_change) in zip(episode.egos, requests, strict=True)
        ]
        finals = self._drive_many(episode, seq, drives)
        self._sumo.stepped(self._api, drives[0].ego.id)
        endings = list(finals.values())  # in the order the drives ended
        reported: list[tuple[str, Observation]] = []
        truncated = False
        for drive in drives:
            ego = drive.ego
            obs = finals.get(ego.id) if finals else None
            if obs is None:
                action, events = drive.outcome()
                obs = self._judge(episode, ego, seq, events, action, traffic=False)
                if obs.reason:
                    endings.append(obs)
                    truncated = truncated or obs.truncated
            reported.append((ego.id, obs))
        if truncated:  # the time limit: every ego's at once
            reported = [
                (ego_id, obs if obs.reason else ended(obs, EndReason.TIME_LIMIT))
                for ego_id, obs in reported
            ]
        joined = self._join(episode, episode.share, seq) if episode.share and not truncated else []
        traffic = self._traffic(episode)  # all of the frame observed before anyone leaves
        if endings or truncated:
            self._take_out(
                [ego_id for ego_id, obs in reported if obs.reason and ego_id not in finals]
            )
            episode.egos = [
                d.ego for d, (_, obs) in zip(drives, reported, strict=True) if not obs.reason
            ] + episode.egos[len(drives) :]  # and those that joined
        reported += joined
        episode.done = not episode.egos
        time = self._api.simulation.getTime()
        last = endings[-1].reason if endings and episode.done else ""
        return multi_observation(seq, time, reported, truncated, last, traffic)

    def _join(self, episode: _Episode, draw: ShareDraw, seq: int) -> list[tuple[str, Observation]]:
        """The vehicles that entered during the decision and join as egos now, at its end
        (SUMO drove them until then), each with its first observation."""
        joining = draw.joining()
        if not joining:  # most decisions
            return []
        present = set(self._api.vehicle.getIDList())
        action = AppliedAction(0.0, 0, 0.0, 0)
        joined = []
        for vehicle in joining:
            if vehicle in present:  # not already gone again (a very long decision)
                ego = self._take_over(episode, vehicle)
                joined.append((vehicle, self._observe(episode, ego, seq, QUIET, action, False)))
        return joined

    def _drive_many(
        self, episode: _Episode, seq: int, drives: list[Drive]
    ) -> dict[str, Observation]:
        """Run the decision's simulation steps for every ego at once. An ego that collides or
        arrives is judged at that simulation step and taken out; the others drive on (all
        gone: the decision stops, unless egos may join it, ``ego_share``). Returns those egos'
        last observations, in the order their drives ended."""
        api = self._api
        simulation, vehicle = api.simulation, api.vehicle
        finals: dict[str, Observation] = {}
        active = drives
        for _ in range(episode.substeps):
            if not episode.sumo_drives:
                for drive in active:
                    drive.applied(*self._apply(episode, drive.ego.id, drive.request))
            api.simulationStep()
            if episode.share is not None:
                episode.share.entered += simulation.getDepartedIDList()
            partners = collision_partners(simulation.getCollisions())
            arrived = simulation.getArrivedIDList()
            teleports = simulation.getStartingTeleportIDList()
            if episode.sumo_drives:
                for drive in active:
                    gone = drive.ego.id in arrived
                    acceleration = 0.0 if gone else vehicle.getAcceleration(drive.ego.id)
                    drive.applied(acceleration, AccelerationLimit.SIMULATOR)
            ending = [
                d
                for d in active
                if self._progress(d, partners, arrived, teleports, episode.signals)
            ]
            if ending:
                for drive in ending:  # every one observed before any is taken out
                    action, events = drive.outcome()
                    finals[drive.ego.id] = self._judge(
                        episode, drive.ego, seq, events, action, traffic=False
                    )
                self._take_out([d.ego.id for d in ending if not d.end_of_road])
                active = [d for d in active if d.ego.id not in finals]
                if not active and episode.share is None:  # a share's may still join
                    break
        return finals

    def _progress(
        self,
        drive: Drive,
        partners: dict[str, tuple[str, str]],
        arrived: Any,
        teleports: Any,
        signals: Programmes | None,
    ) -> bool:
        """Record what one simulation step did to an ego; True if its drive ended in it (a
        collision, its arrival)."""
        ego = drive.ego
        if teleports and ego.id in teleports:
            drive.teleported = True
        partner = partners.get(ego.id) if partners else None
        if partner is not None:
            drive.collision_with, drive.collision_type = partner
            return True
        if ego.id in arrived:
            drive.end_of_road = True
            return True
        if signals is not None and ego.red_lights.passed_red(self._api, ego.id):
            drive.red_light = True
        self._lane_change_steps(drive)
        return False

    def _lane_change_steps(self, drive: Drive) -> None:
        """After a simulation step: a signalled change that started, a change that completed
        or was given up."""
        if drive.signalled_from is not None:
            self._signalled_start(drive, drive.signalled_from)
        ego = drive.ego
        if ego.lane_change is not None:
            drive.completed, drive.aborted = self._lane_change_progress(ego, ego.lane_change)

    def _take_out(self, ego_ids: list[str]) -> None:
        """Remove egos whose drive has ended from the simulation (those still in it)."""
        if not ego_ids:
            return
        vehicle = self._api.vehicle
        present = set(vehicle.getIDList())
        for ego_id in ego_ids:
            if ego_id in present:
                vehicle.remove(ego_id)

    # ----------------------------------------------------------------------- measures

    def _new_ssm_log(self) -> Path:
        """A fresh file name for the next episode's SSM log."""
        if self._logs is None:
            self._logs = Path(tempfile.mkdtemp(prefix="av-bridge-ssm-"))
        return self._logs / f"ssm-{next(self._log_numbers)}.xml"

    def _drop_old_logs(self, keep: Path | None) -> None:
        """Delete the logs of abandoned episodes (SUMO has written them out by now)."""
        if self._logs is not None:
            for old in self._logs.iterdir():
                if old != keep:
                    old.unlink(missing_ok=True)

    def _conflicts(self, episode: _Episode, log: Path) -> Safety:
        """The ego's conflicts from the SSM log, which SUMO writes out when the simulation is
        closed: load the small built-in ``cf`` road (not the scenario again, whose own outputs
        would be overwritten), read the log, delete it. Over TraCI a load is acknowledged before
        the old simulation has closed; a round trip after it waits for that."""
        config = self._files(BUILTIN_SCENARIOS["cf"], {}, 0).config
        self._load(["-c", str(config), *_forced_args(-1)])
        self._api.simulation.getTime()
        try:
            return ssm.read_log(log, episode.dt, since=episode.ego.end.entry_time)
        except ssm.LogError as exc:
            raise BackendError(ErrorCode.SIMULATOR_ERROR, str(exc)) from exc
        finally:
            log.unlink(missing_ok=True)

    def _leader_trip(self, episode: _Episode) -> LeaderTrip | None:
        """The leader-at-entry's trip: the simulation runs on (without the ego) until it
        arrives, for at most `_run_on` seconds of simulation and `CEILING_WALL_S` of wall-clock
        time; arrival nil if it has not."""
        api = self._api
        if not episode.leader_id:
            return None
        end = api.simulation.getTime() + self._run_on(episode)
        wall_end = time.monotonic() + CEILING_WALL_S
        while episode.leader_arrival is None and api.simulation.getTime() < end:
            if time.monotonic() >= wall_end:
                break  # the reply cannot wait longer: the ceiling stays unknown
            api.simulationStep()
            if episode.leader_id in api.simulation.getArrivedIDList():
                episode.leader_arrival = api.simulation.getTime()
        arrival = episode.leader_arrival
        average = (
            None if arrival is None else episode.route_length / (arrival - episode.leader_depart)
        )
        return LeaderTrip(episode.leader_id, episode.leader_depart, arrival, average)

    def _run_on(self, episode: _Episode) -> float:
        """Simulated seconds to wait for the leader-at-entry to arrive: what its remaining
        route takes at `CEILING_MIN_SPEED`, and a minute, at most `CEILING_HORIZON` (0 when it
        has arrived, or no longer knows a way to the end of the route)."""
        api, leader = self._api, episode.leader_id
        if episode.leader_arrival is not None or leader not in api.vehicle.getIDList():
            return 0.0
        last = api.vehicle.getRoute(leader)[-1]
        remaining = api.vehicle.getDrivingDistance(leader, last, api.lane.getLength(f"{last}_0"))
        if not 0.0 <= remaining < 1e9:  # SUMO's INVALID_DOUBLE_VALUE: no way there
            return 0.0
        return min(CEILING_HORIZON, 60.0 + remaining / CEILING_MIN_SPEED)

    # ----------------------------------------------------------------------- observation

    def _lane_length(self, lane_id: str) -> float:
        """A lane's length (m), asked of SUMO once per network."""
        length = self._lane_lengths.get(lane_id)
        if length is None:
            length = self._lane_lengths[lane_id] = self._api.lane.getLength(lane_id)
        return length

    def _lane(self, episode: _Episode, ego_id: str, lane_id: str | None = None) -> tuple[int, int]:
        """The ego's lane index and the number of lanes of its edge (one query when cached)."""
        api = self._api
        if lane_id is None:
            lane_id = api.vehicle.getLaneID(ego_id)
        known = episode.lanes.get(lane_id)
        if known is None:
            road = api.lane.getEdgeID(lane_id)
            known = episode.lanes[lane_id] = (
                api.vehicle.getLaneIndex(ego_id),
                api.edge.getLaneNumber(road),
            )
        return known

    def _observe(
        self,
        episode: _Episode,
        ego: EgoState,
        seq: int,
        events: Events,
        action: AppliedAction,
        traffic: bool = True,
    ) -> Observation:
        """`ego`'s observation now (with the traffic if asked for and `traffic`); kept as its
        last."""
        vehicle = self._api.vehicle
        ego_id = ego.id
        speed = vehicle.getSpeed(ego_id)  # first: raises if the ego has gone
        acceleration = vehicle.getAcceleration(ego_id)
        lane_id = vehicle.getLaneID(ego_id)
        lane, lane_count = self._lane(episode, ego_id, lane_id)
        position = ego.entry_offset + vehicle.getDistance(ego_id)
        state = Ego(
            speed=speed,
            acceleration=acceleration,
            lane=lane,
            lane_count=lane_count,
            position=position,
            speed_limit=self._api.lane.getMaxSpeed(lane_id),
            changing_lane=0 if ego.lane_change is None else ego.lane_change.direction,
        )
        lane_position = vehicle.getLanePosition(ego_id)
        best_lanes = vehicle.getBestLanes(ego_id)
        road = road_ahead(best_lanes, lane_id, lane_position, self._lane_length)
        onward = next((entry[5] for entry in best_lanes if entry[0] == lane_id), ())
        # A junction ahead on the route only where the lane leads into another (not on `cf`).
        links = vehicle.getNextLinks(ego_id) if road is not None and len(onward) > 1 else ()
        signal = NO_SIGNAL
        if episode.signals is not None:
            now, inside = self._api.simulation.getTime(), ego.red_lights.inside(self._api, ego_id)
            signal = next_signal(self._api, ego_id, episode.signals, now, inside)
        if road is not None:
            to_junction = self._lane_length(lane_id) - lane_position
            ego.approach_lane = lane_id
            foes = self._priority_foes(episode, ego_id, lane_id, links, to_junction)
            at_light = abs(signal.distance - to_junction) <= SAME_LINE
            yellow_left = signal.switch if at_light else math.inf
            line = stop_line(
                links, to_junction, speed, state.speed_limit, foes, yellow_left,
                state.speed_limit,  # the light is at the end of this lane
            )  # fmt: skip
            ego.give_way = ROAD_RANGE if not links or links[0][1] else max(to_junction, 0.0)
            ego.across = 0.0
            if links and 0.0 <= to_junction <= ACROSS_LOOK:
                ego.across = to_junction + self._inside_length(str(links[0][4]))
            if line >= ROAD_RANGE and not episode.one_way:
                line = self._stop_at_waiting_point(episode, ego, links, to_junction, speed)
            if line >= ROAD_RANGE and not episode.one_way:
                line = self._stop_further(episode, ego_id, links, to_junction, speed)
            road = replace(road, stop_line=line)
        if road is None:  # on a junction
            ego.give_way, ego.across = ROAD_RANGE, 0.0
            last = ego.last
            driven = position - last.ego.position if last is not None else 0.0
            road = carried(last.road if last is not None else None, driven, lane, lane_count)
            if not episode.one_way:  # where it may wait inside for foes (turning across them)
                line = self._stop_within(episode, ego, lane_id, lane_position)
                if line >= ROAD_RANGE:
                    line = self._stop_after_junction(episode, ego_id, lane_id, lane_position)
                line = min(line, self._standing_inside(episode, ego, lane_id, lane_position))
                road = replace(road, stop_line=line)
        if episode.signals is not None:
            road = replace(
                road,
                stop_line=min(
                    road.stop_line,
                    signal_line(
                        signal,
                        speed,
                        self._limit_before(lane_id, lane_position, onward, signal.distance)
                        if signal.state == SignalState.YELLOW
                        else math.inf,
                    ),
                ),
                signal_distance=signal.distance,
                signal_state=signal.state,
                signal_switch=signal.switch,
            )
        if ego.route:
            ego.route_index = vehicle.getRouteIndex(ego_id)
        frame = None if episode.curved else self._frame(ego_id)
        ego_min_gap = ego.min_gap
        sensed = self.sensor_range
        leader = vehicle.getLeader(ego_id, sensed)
        if not leader or not leader[0]:
            leader = self._leader_beyond(onward, links, lane_id, lane_position, ego_min_gap)
        if road is not None and not lane_id.startswith(":"):
            to_end = self._lane_length(lane_id) - lane_position
            if to_end <= PARTIAL_LOOK:
                partial = self._rear_on_lane(lane_id, to_end, ego_min_gap)
                if partial is not None and (not leader or not leader[0] or partial[1] < leader[1]):
                    leader = partial
        follower = vehicle.getFollower(ego_id, sensed)
        # SUMO finds no neighbour where there is no lane: on a built-in road, skip those queries.
        left = not episode.one_way or lane + 1 < lane_count
        right = not episode.one_way or lane > 0
        nearest, none = self._nearest, ()
        neighbours = Neighbours(
            left_leader=nearest(
                episode, vehicle.getNeighbors(ego_id, 0b010) if left else none, ego_min_gap, frame
            ),
            left_follower=nearest(
                episode, vehicle.getNeighbors(ego_id, 0b000) if left else none, None, frame
            ),
            leader=nearest(
                episode, (leader,) if leader and leader[0] else none, ego_min_gap, frame, ego_id
            ),
            follower=nearest(
                episode, (follower,) if follower and follower[0] else none, None, frame
            ),
            right_leader=nearest(
                episode, vehicle.getNeighbors(ego_id, 0b011) if right else none, ego_min_gap, frame
            ),
            right_follower=nearest(
                episode, vehicle.getNeighbors(ego_id, 0b001) if right else none, None, frame
            ),
        )
        obs = Observation(
            seq=seq,
            time=self._api.simulation.getTime(),
            ego=state,
            neighbours=neighbours,
            events=events,
            action=action,
            traffic=self._traffic(episode) if traffic else None,
            road=road,
        )
        ego.last = obs
        return obs

    def _rear_on_lane(
        self, lane_id: str, to_end: float, ego_min_gap: float
    ) -> tuple[str, float] | None:
        """The nearest vehicle that has entered the junction at the end of the ego's lane,
        `to_end` m ahead, by any of its connections, with its rear still on that lane, as
        (id, gap less the ego's minGap) like `vehicle.getLeader`; None where none has. SUMO's
        leader search follows the ego's own way into the junction and may not report one
        turning elsewhere (the shipped roads policy drove into such a car, standing 2.5 m
        ahead, on the São Paulo export once it had vanished from its observation). Each
        connection's junction lanes are followed past a waiting point inside the junction: a
        long vehicle turning across oncoming traffic may stand beyond it with its rear still
        on the ego's lane (a 12 m truck on Greenville, which the policy drove into)."""
        lane_api, vehicle = self._api.lane, self._api.vehicle
        nearest: tuple[str, float] | None = None
        for link in lane_api.getLinks(lane_id):
            inside, via = 0.0, str(link[4])  # m of the junction before `via`
            for _ in range(MAX_FURTHER_LINKS):
                if not via.startswith(":"):
                    break
                for other in lane_api.getLastStepVehicleIDs(via):
                    behind = vehicle.getLength(other) - inside - vehicle.getLanePosition(other)
                    if behind <= 0.0:
                        continue  # all of it inside the junction
                    gap = to_end - behind - ego_min_gap
                    if nearest is None or gap < nearest[1]:
                        nearest = (other, gap)
                inside += self._lane_length(via)
                onward = lane_api.getLinks(via)
                via = str(onward[0][4]) if onward else ""
        return nearest

    def _traffic(self, episode: _Episode) -> Traffic | None:
        """Every vehicle but the egos (reset option ``report_traffic``), or None."""
        if not episode.measures.report_traffic:
            return None
        return observe_traffic(self._api, episode.ids, self.sensor_range, episode.min_gaps)

    def _frame(self, ego_id: str) -> tuple[float, float, float, float]:
        """The ego's position and the unit normal to the left of its heading."""
        x, y = self._api.vehicle.getPosition(ego_id)
        heading = math.radians(self._api.vehicle.getAngle(ego_id))
        return (x, y, -math.cos(heading), math.sin(heading))

    def _stop_within(
        self, episode: _Episode, ego: EgoState, lane_id: str, lane_position: float
    ) -> float:
        """The stop line on a junction's internal lane: the waiting point inside the junction
        (SUMO's internal junction) of a vehicle turning across oncoming traffic, while the
        foes with priority over its way on (from the lane it came from) are too close;
        `ROAD_RANGE` where the way on is open. Once the light it entered at has turned red the
        junction is cleared by those inside it: the ego goes, but not ahead of a car already
        inside that comes across its way, nor of one on its fresh green too fast to stop before
        their ways meet (SUMO's drivers starting on their green do not wait for it, and
        netconvert's programmes have no all-red time: Greenville and `urban`, collisions); those
        that can stop wait for it (waiting for them, it stood through a cycle on Greenville).
        Past the waiting point nothing is left to wait at: the end of its lane is the
        junction's exit, beyond the ways it crosses, and an ego braking for it stood across a
        car starting on its green (Greenville, IDM + MOBIL, a collision): it clears."""
        lanes = self._api.lane
        links = lanes.getLinks(lane_id)
        if not links or not ego.approach_lane:
            return ROAD_RANGE
        own = next(
            (link[5] for link in lanes.getLinks(ego.approach_lane) if link[0] == links[0][0]), ""
        )
        to_junction = self._lane_length(lane_id) - lane_position
        speed = self._api.vehicle.getSpeed(ego.id)
        foes = self._priority_foes(episode, ego.id, ego.approach_lane, links, to_junction)
        limit = self._api.lane.getMaxSpeed(lane_id)
        if own in YELLOW_STATES and self._stranded(episode, ego, lane_id, links, to_junction):
            return max(to_junction, 0.0)
        if own in TURNED:  # its light has turned red: it clears, those that cannot wait first
            if episode.junction_foes is None:
                episode.junction_foes = JunctionFoes(self._api)
            junction = episode.junction_foes
            via, ego_exit = str(links[0][4]), to_junction + links[0][7]
            if not junction.waits_inside(lane_id):
                if not self._at_waiting_point(ego, lane_id, lane_position, speed):
                    return ROAD_RANGE  # past its waiting point: stopping would stand in the way
                via, ego_exit, line = lane_id, to_junction, 0.0  # it stands where it is
            else:
                line = max(to_junction, 0.0)  # at the waiting point
            inside = junction.inside(ego.approach_lane, via, ego_exit) if via else ()
            coming = foes + junction.of(ego.approach_lane, str(links[0][0]), ego_exit)
            fast = tuple(f for f in coming if f.speed**2 > 2.0 * FOE_DECELERATION * f.distance)
            return line if too_close(inside + fast, speed, limit) else ROAD_RANGE
        return stop_line(links, to_junction, speed, limit, foes)

    def _at_waiting_point(
        self, ego: EgoState, lane_id: str, lane_position: float, speed: float
    ) -> bool:
        """Whether the ego, on the junction lane `lane_id` just after the waiting point of
        its turn, can stop within `WAITING_POINT_OVERSHOOT` of that point (at
        `WAITING_POINT_DECELERATION`): it overshot it at a crawl, braking for a car that had
        waited there for it and moved off, and stands where the waiting point would have held
        it (Greenville: past it by a few centimetres at 0.1 m/s, the ego drove on into that
        car crossing its way)."""
        stops_at = lane_position + speed * speed / (2.0 * WAITING_POINT_DECELERATION)
        if stops_at > WAITING_POINT_OVERSHOOT:
            return False
        lanes = self._api.lane
        target = str(lanes.getLinks(lane_id)[0][0]) if lanes.getLinks(lane_id) else ""
        first = next(
            (str(link[4]) for link in lanes.getLinks(ego.approach_lane) if link[0] == target), ""
        )
        if not first or first == lane_id:
            return False
        onward = lanes.getLinks(first)
        return bool(onward) and str(onward[0][4]) == lane_id

    def _limit_before(
        self, lane_id: str, lane_position: float, onward: Any, distance: float
    ) -> float:
        """The lowest speed limit on the ego's way to a stop line `distance` m ahead: its lane's
        and those of the junction lanes and lanes after it on its route (`onward`: its best
        lanes' next lanes, its own first; on a junction's lane, the lane it leads to) that begin
        before the line. SUMO holds the ego to a lane's limit even with its checks off (at the
        ego's braking bound): a light's yellow that the ego would reach in time at its speed it
        does not reach when the limit beyond the junction before it is half as high (São
        Paulo: a red light)."""
        lanes = self._api.lane
        limit = lanes.getMaxSpeed(lane_id)
        ahead = self._lane_length(lane_id) - lane_position  # to the end of `previous`
        following = [str(lane) for lane in onward if lane != lane_id]
        if not following and lane_id.startswith(":"):
            following = [str(link[0]) for link in lanes.getLinks(lane_id)[:1]]
        previous = lane_id
        for lane in following[:MAX_LIMIT_LANES]:
            if ahead >= distance - SAME_LINE:
                break  # the line is at the end of `previous`
            via = next((str(link[4]) for link in lanes.getLinks(previous) if link[0] == lane), "")
            if via:
                limit = min(limit, lanes.getMaxSpeed(via))
                ahead += self._inside_length(via)
            limit = min(limit, lanes.getMaxSpeed(lane))
            ahead += self._lane_length(lane)
            previous = lane
        return limit

    def _stranded(
        self, episode: _Episode, ego: EgoState, lane_id: str, links: Any, to_junction: float
    ) -> bool:
        """Whether the ego, inside the junction before the waiting point of a turn across
        oncoming traffic (`lane_id`) and able to stop there, would not have left the junction
        (its rear past the ways it crosses after the waiting point, accelerating at
        `CLEARING_ACCELERATION`) before its yellow light turns red, while a car drives up to
        one of those ways (`JunctionFoes.driving_up`). It then waits there: netconvert's
        programmes have no all-red time, so the crossing road's green starts with that red,
        and SUMO's drivers on it do not wait for a car still inside that they judge they pass
        first (Greenville: the ego left its waiting point at the end of the yellow and was hit
        3 s after its red by a car that had braked for its own red and drove on at its green).
        Cars that stand in a queue at their red start slowly and see the ego inside (an ego
        waiting for them in a junction of `DRT`'s joined clusters stood there until the trip
        jammed). Standing there it is clear of the crossing road's ways; it goes once they
        have passed, or with its next green. Judged inside the junction only, under the light
        it passed (`RedLightWatch.passed`)."""
        after = str(links[0][4])  # the junction lane after the waiting point
        if episode.signals is None or not ego.red_lights.passed or not after.startswith(":"):
            return False
        if not self._api.vehicle.getLaneID(ego.id).startswith(":"):
            return False  # judged inside the junction, under the light it passed
        speed = self._api.vehicle.getSpeed(ego.id)
        if speed * speed > 2.0 * WAITING_POINT_DECELERATION * max(to_junction, 0.0):
            return False  # too late to stop there: it goes on
        light = ego.red_lights.passed
        index = episode.signals.link_index(light, ego.approach_lane, str(links[0][0]))
        if index < 0:
            return False
        now = self._api.simulation.getTime()
        yellow_left = episode.signals.switch_in(light, index, now)
        to_clear = max(to_junction, 0.0) + self._inside_length(after) + VEHICLE_LENGTH
        limit = self._api.lane.getMaxSpeed(lane_id)
        clearing = time_to_cover(to_clear, speed, limit)
        if clearing <= yellow_left:
            return False
        if episode.junction_foes is None:
            episode.junction_foes = JunctionFoes(self._api)
        return episode.junction_foes.driving_up(ego.approach_lane, after, clearing)

    def _stop_at_waiting_point(
        self, episode: _Episode, ego: EgoState, links: Any, to_junction: float, speed: float
    ) -> float:
        """Approaching a turn across oncoming traffic (the next link's junction lane ends at
        a waiting point inside the junction, SUMO's internal junction): the waiting point's
        stop line (`_stop_within`) once it is within `FURTHER_LOOK` plus the ego's braking
        distance, so that the ego comes slowly enough to stop there while the oncoming stream
        comes (IDM + MOBIL turned left at 18 m/s into oncoming traffic on the Greenville
        export, the waiting point first judged 1.4 m before it). ROAD_RANGE otherwise."""
        if not links or not links[0][4]:
            return ROAD_RANGE
        via = str(links[0][4])
        if episode.junction_foes is None:
            episode.junction_foes = JunctionFoes(self._api)
        if not episode.junction_foes.waits_inside(via):
            return ROAD_RANGE
        look = FURTHER_LOOK + speed * speed / (2.0 * FURTHER_DECELERATION)
        if to_junction + self._lane_length(via) > look:
            return ROAD_RANGE
        return self._stop_within(episode, ego, via, -to_junction)

    def _stop_further(
        self, episode: _Episode, ego_id: str, links: Any, to_junction: float, speed: float
    ) -> float:
        """Where the ego must stop for a junction beyond the next one, its link closed (red,
        giving way to foes too close), while that junction is within `FURTHER_LOOK` of the
        ego (plus the distance it needs to stop): at the end of the lane before it, as SUMO's
        own drivers stop, however short that lane (where it is shorter than the ego, the ego
        stands partly in the junction before: stopping before that one, 10 m farther from the
        conflict, it found no gap in a busy main road in 2 of 10 trips of the test's crossing
        and stood until `jam_patience`). A lane between two junctions may be a metre long
        (netconvert's joined clusters): a driver that looked at the next junction only would be
        inside the first when the second's foes came into view (DRT: a left turn into a
        priority road, 1 m after another junction, ended in a collision). ROAD_RANGE where
        nothing closes the way."""
        distance = to_junction  # to the entrance of the junction of links[index]
        look = FURTHER_LOOK + speed * speed / (2.0 * FURTHER_DECELERATION)
        for index in range(min(len(links) - 1, MAX_FURTHER_LINKS)):
            lane = str(links[index][0])
            between = self._lane_length(lane)
            entrance = distance + self._inside_length(str(links[index][4])) + between
            if entrance > look:
                break
            onward = links[index + 1 :]
            foes = self._priority_foes(episode, ego_id, lane, onward, entrance)
            limit = self._api.lane.getMaxSpeed(lane)
            if stop_line(onward, entrance, speed, limit, foes) < ROAD_RANGE:
                return entrance
            distance = entrance
        return ROAD_RANGE

    def _stop_after_junction(
        self, episode: _Episode, ego_id: str, lane_id: str, lane_position: float
    ) -> float:
        """On a junction's lane: where the ego must stop for the next junction when its link
        is closed and it lies within `FURTHER_LOOK` (`_stop_further`): at the end of the lane
        between them. ROAD_RANGE otherwise."""
        links = self._api.vehicle.getNextLinks(ego_id)
        out = self._api.lane.getLinks(lane_id)
        if not links or not out:
            return ROAD_RANGE  # the end of the route
        between = str(out[0][0])
        rest = self._inside_length(str(out[0][4]))  # beyond a waiting point inside
        distance = self._lane_length(lane_id) - lane_position + rest + self._lane_length(between)
        speed = self._api.vehicle.getSpeed(ego_id)
        if distance > FURTHER_LOOK + speed * speed / (2.0 * FURTHER_DECELERATION):
            return ROAD_RANGE
        foes = self._priority_foes(episode, ego_id, between, links, distance)
        limit = self._api.lane.getMaxSpeed(between)
        closed = stop_line(links, distance, speed, limit, foes) < ROAD_RANGE
        return distance if closed else ROAD_RANGE

    def _standing_inside(
        self, episode: _Episode, ego: EgoState, lane_id: str, lane_position: float
    ) -> float:
        """On a junction's lane: m to a vehicle of another of its lanes whose body is on the
        ego's way ahead (`JunctionFoes.standing_ahead`); ROAD_RANGE where none is."""
        if not ego.approach_lane:
            return ROAD_RANGE
        if episode.junction_foes is None:
            episode.junction_foes = JunctionFoes(self._api)
        ahead = episode.junction_foes.standing_ahead(ego.approach_lane, lane_id, lane_position)
        return min(ahead, ROAD_RANGE)

    def _inside_length(self, via: str) -> float:
        """m through a junction from the start of its lane `via`: that lane and those after
        a waiting point inside it (SUMO's internal junction); 0 for no junction lane."""
        total, lane = 0.0, via
        for _ in range(MAX_FURTHER_LINKS):
            if not lane.startswith(":"):
                break
            total += self._lane_length(lane)
            onward = self._api.lane.getLinks(lane)
            lane = str(onward[0][4]) if onward else ""
        return total

    def _priority_foes(
        self, episode: _Episode, ego_id: str, from_lane: str, links: Any, to_junction: float
    ) -> tuple[Foe, ...]:
        """The foes the ego must give way to where it takes the first of `links` from
        `from_lane`. Where that link gives way and is open (`yields_at`): SUMO's junction foes
        on its junction lane (`vehicle.getJunctionFoes`, which knows where their ways meet),
        or where SUMO names none, the vehicles coming on the lanes with priority over its
        connection (`JunctionFoes.of`; where the junction lane leads to a waiting point inside
        the junction, a turn across oncoming traffic, those are judged there, `_stop_within`);
        on any link, near the junction, the vehicles inside it across the ego's way
        (`JunctionFoes.inside`)."""
        if not links:
            return ()
        link = links[0]
        ego_exit = to_junction + link[7]
        found: tuple[Foe, ...] = ()
        via = yields_at(links)
        if via:
            vehicle = self._api.vehicle
            found = tuple(
                Foe(foe_distance, foe_exit, vehicle.getSpeed(foe_id), ego_exit)
                for (foe_id, _, foe_distance, ego_exit, foe_exit, ego_lane, _, ego_yields,
                     foe_yields) in vehicle.getJunctionFoes(ego_id, to_junction + 1.0)
                if ego_lane == via and ego_yields and not foe_yields
            )  # fmt: skip
        if episode.one_way:
            return found
        if episode.junction_foes is None:
            episode.junction_foes = JunctionFoes(self._api)
        foes = episode.junction_foes
        if via and not found and not foes.waits_inside(via):  # inside: judged there
            found = foes.of(from_lane, link[0], ego_exit)
        speed = self._api.vehicle.getSpeed(ego_id)
        if to_junction <= max(BLOCKING_LOOK, speed * BLOCKING_TIME) and link[4]:
            found += foes.inside(from_lane, link[4], ego_exit)
        return found

    def _leader_beyond(
        self,
        onward: Any,
        links: Any,
        lane_id: str,
        lane_position: float,
        ego_min_gap: float,
    ) -> tuple[str, float] | None:
        """The nearest vehicle ahead on the lanes the ego's lane leads into along its route
        (`onward`, its own first: its best lanes' next lanes, `vehicle.getBestLanes`; the
        junctions between them `links`, `vehicle.getNextLinks`), as
        (id, gap less the ego's minGap) like `vehicle.getLeader`, or None within the sensor
        range. SUMO's own search stops at a junction whose way it judges closed to the ego, so
        that a jam standing beyond it was not seen (SUMO's ramp: an off-ramp's queue, first
        seen at 73 m from 32 m/s). A vehicle on a junction itself is not looked for."""
        vehicle, seen = self._api.vehicle, self._lane_length(lane_id) - lane_position
        for index, lane in enumerate(onward[1:]):
            if index < len(links):
                seen += links[index][7]  # the junction's lane
            if seen >= self.sensor_range:
                return None
            on_lane = self._api.lane.getLastStepVehicleIDs(lane)
            if on_lane:
                last = min(on_lane, key=vehicle.getLanePosition)
                rear = vehicle.getLanePosition(last) - vehicle.getLength(last)
                return last, seen + rear - ego_min_gap
            seen += self._lane_length(lane)
        return None

    def _bumper_gap(self, ego_id: str, leader: str) -> float:
        """From the ego's front to the leader's rear, along the ego's heading (m; negative where
        they overlap), from their positions (SUMO's is the front bumper's middle)."""
        vehicle = self._api.vehicle
        x, y = vehicle.getPosition(ego_id)
        heading = math.radians(vehicle.getAngle(ego_id))
        other_x, other_y = vehicle.getPosition(leader)
        other_heading = math.radians(vehicle.getAngle(leader))
        length = vehicle.getLength(leader)
        rear_x = other_x - length * math.sin(other_heading)
        rear_y = other_y - length * math.cos(other_heading)
        return (rear_x - x) * math.sin(heading) + (rear_y - y) * math.cos(heading)

    def _nearest(
        self,
        episode: _Episode,
        found: Any,
        ego_min_gap: float | None,
        frame: tuple[float, float, float, float] | None,
        ego_id: str = "",
    ) -> Neighbour:
        """The closest of (id, distance) pairs as a Neighbour with the net bumper gap.

        SUMO's leader distance excludes the ego's minGap, its follower distance the follower's:
        `ego_min_gap` is given for leaders, None for followers. Its lateral offset is measured
        across the ego's heading (`frame`), or 0 without a frame (one curved lane). SUMO reports
        a leader on a junction closer than the ego's minGap at distance 0 (it clamps such a
        "link leader's" gap, which may be negative): given `ego_id`, that gap is measured from
        the two vehicles' positions instead.
        """
        api = self._api
        if not found:
            return self._absent
        other, distance = found[0] if len(found) == 1 else min(found, key=_second)
        if not -UNMEASURED <= distance <= UNMEASURED:  # SUMO's -DBL_MAX: not measured
            return self._measured(episode, other, ego_min_gap is not None, frame)
        if ego_min_gap is None:
            min_gap = episode.min_gaps.get(other)
            if min_gap is None:
                min_gap = episode.min_gaps[other] = api.vehicle.getMinGap(other)
            gap = distance + min_gap
        else:
            gap = distance + ego_min_gap
            if ego_id and distance <= 0.0:  # not below 0: it may be beside, on a junction
                gap = min(gap, max(self._bumper_gap(ego_id, other), 0.0))
        if gap > self.sensor_range:
            return self._absent
        lateral = 0.0
        if frame is not None:
            x, y, normal_x, normal_y = frame
            other_x, other_y = api.vehicle.getPosition(other)
            lateral = (other_x - x) * normal_x + (other_y - y) * normal_y
        return Neighbour(True, gap, lateral, api.vehicle.getSpeed(other), other)

    def _measured(
        self,
        episode: _Episode,
        other: str,
        ahead: bool,
        frame: tuple[float, float, float, float] | None,
    ) -> Neighbour:
        """A neighbour SUMO found but could not measure the distance to (it reports
        -DBL_MAX, e.g. for a vehicle beside the ego on a junction's lanes): its gap from the
        two positions along the ego's heading (`frame`), absent if that puts it out of range
        or on the other side, or where there is no frame (the ring)."""
        if frame is None:
            return self._absent
        vehicle = self._api.vehicle
        x, y, normal_x, normal_y = frame
        other_x, other_y = vehicle.getPosition(other)
        along = (other_x - x) * normal_y - (other_y - y) * normal_x  # heading = (n_y, -n_x)
        lateral = (other_x - x) * normal_x + (other_y - y) * normal_y
        ego_length = VEHICLE_LENGTH
        gap = along - vehicle.getLength(other) if ahead else -along - ego_length
        if not -2.0 * ego_length <= gap <= self.sensor_range:
            return self._absent
        return Neighbour(True, gap, lateral, vehicle.getSpeed(other), other)

    def _arrival_observation(
        self,
        episode: _Episode,
        ego: EgoState,
        seq: int,
        events: Events,
        action: AppliedAction,
        traffic: bool = True,
    ) -> Observation:
        """The ego has left the network: extrapolate its last observed state by one decision."""
        last = ego.last
        assert last is not None
        elapsed = episode.dt * episode.substeps
        state = replace(
            last.ego,
            speed=max(0.0, last.ego.speed + action.acceleration * elapsed),
            acceleration=action.acceleration,
            position=episode.route_length,
        )
        return replace(
            last,
            seq=seq,
            time=self._api.simulation.getTime(),
            ego=state,
            events=events,
            action=action,
            traffic=self._traffic(episode) if traffic else None,
        )

    # ----------------------------------------------------------------------- lifecycle

    def _broken(self, error: BaseException | None = None) -> None:
        """After a SUMO failure, start afresh on the next reset."""
        self._episode = None
        if error is not None and self._sumo.survives(error):
            return  # the next reset reloads the same SUMO
        if self._running:
            with contextlib.suppress(*self._errors):  # already gone: start() will follow
                self._sumo.close(self._api)
        self._running = False

    def close(self) -> None:
        self._broken()
        if self._logs is not None:
            shutil.rmtree(self._logs, ignore_errors=True)
            self._logs = None
        if self._episode_files is not None:
            shutil.rmtree(self._episode_files, ignore_errors=True)
            self._episode_files = None


def _forced_args(teleport: float) -> list[str]:
    """`_FORCED_ARGS` with SUMO's time to teleport a stuck vehicle (-1: never)."""
    args = list(_FORCED_ARGS)
    args[args.index("--time-to-teleport") + 1] = f"{teleport:g}"
    return args


def _second(pair: tuple[str, float]) -> float:
    return pair[1]


def _route_needs(ego: EgoState, direction: int) -> bool:
    """The ego's route needs a change in `direction` (by the road of its last observation)."""
    road = ego.last.road if ego.last is not None else None
    return road is not None and road.lanes_to_change * direction > 0
