"""Typed, immutable messages of the bridge protocol.

Requests go from the learner (client) to the simulator (server): `Hello`, `Reset`, `Step`,
`Close`. Replies go back: `Welcome`, `Observation`, `Error`, `Bye`. Every message maps one to one
onto a msgpack map on the wire (see `protocol.codec` and docs/protocol.md); the class attribute
`TYPE` is the value of that map's ``type`` key.

Units are SI throughout: metres, seconds, m/s, m/s^2. Lane indices count from 0 at the rightmost
lane; lateral offsets are positive to the left.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import ClassVar

OptionValue = bool | int | float | str | None

ROAD_RANGE = 1000.0
"""Metres of road ahead that `Road` describes: a lane that goes on farther along the ego's route,
or reaches its end, is reported at this distance (since protocol 1.6)."""
SIGNAL_HORIZON = 120.0
"""Seconds ahead that `Road.signal_switch` looks: a signal state that lasts longer (an ``off``
light, a long phase) is reported at this time (since protocol 1.8)."""
MAX_ROUTE_EDGES = 1024
"""The most edges `Route.edges` lists (the protocol's longest array, §5)."""


class LaneChange(IntEnum):
    """Lane-change command of a step: -1 right, 0 keep, +1 left (the paper's RLC/LK/LLC)."""

    RIGHT = -1
    KEEP = 0
    LEFT = 1


class EndReason(StrEnum):
    """Why an episode ended (`Observation.reason`; "" while it runs)."""

    COLLISION = "collision"
    STOPPED = "stopped"
    """Unreasonably slow with no leader close ahead, for ``stop_patience`` seconds."""
    END_OF_ROAD = "end_of_road"
    EGO_LOST = "ego_lost"
    """The simulator lost the ego without an arrival (a teleport, a removal)."""
    TIME_LIMIT = "time_limit"
    """The only reason of a truncated episode: every other one terminates it."""
    LANE_END = "lane_end"
    """Stood at the end of a lane that does not continue its route, for ``lane_end_patience``
    seconds: a merge not made, an exit missed (since protocol 1.6)."""
    RED_LIGHT = "red_light"
    """Passed a red light (`Events.red_light`), where the reset option ``end_on_red_light``
    asks for the episode to end there (since protocol 1.8)."""
    JAMMED = "jammed"
    """Stood (slower than ``stop_speed``) for ``jam_patience`` seconds, whatever held it: a
    jam that does not clear, a gridlock (since protocol 1.8)."""

    @property
    def terminates(self) -> bool:
        """True if the episode is terminated (an MDP end), False if it is truncated."""
        return self is not EndReason.TIME_LIMIT


class LaneChangeRefusal(StrEnum):
    """Why a lane-change command was not started (`AppliedAction.lane_change_refused`)."""

    GAP_TOO_SMALL = "gap_too_small"
    """The target lane has no safe gap (the paper's state G)."""
    NO_LANE = "no_lane"
    """There is no lane on that side."""
    IN_PROGRESS = "in_progress"
    """A lane change is still under way (`Ego.changing_lane` is not 0)."""
    SIMULATOR_DRIVES = "simulator_drives"
    """The simulator drives the ego (option ``ego_driver = "sumo"``)."""


class SignalState(StrEnum):
    """The state of the ego's link at the next traffic light on its route (`Road.signal_state`,
    since protocol 1.8)."""

    NONE = ""
    """No traffic light within `ROAD_RANGE` on the route."""
    GREEN = "green"
    """The way is open (with priority or, a permissive green, giving way to foes)."""
    YELLOW = "yellow"
    """About to turn red: stop if that can be done safely."""
    RED = "red"
    """Closed: red, or red-yellow (about to turn green)."""
    OFF = "off"
    """The light is off or blinking: the junction's right of way applies (`Road.stop_line`)."""


class CollisionType(StrEnum):
    """Where a collision happened (`Events.collision_type`, since protocol 1.8)."""

    LANE = "lane"
    """On a lane: into a leader, a vehicle alongside, a follower."""
    JUNCTION = "junction"
    """Inside a junction: with a vehicle crossing or merging on another link."""


class AccelerationLimit(StrEnum):
    """Why the applied acceleration differs from the requested one
    (`AppliedAction.acceleration_limited_by`; "" when applied as asked)."""

    BOUNDS = "bounds"
    """Clipped to the action schema's bounds."""
    SPEED_LIMIT = "speed_limit"
    """Reduced so that the speed stays within the road's limit."""
    STANDSTILL = "standstill"
    """Raised so that the speed does not go below zero."""
    SIMULATOR = "simulator"
    """The simulator drives the ego."""


# --------------------------------------------------------------------------- requests


@dataclass(frozen=True, slots=True)
class Hello:
    """Opens a session: the client's protocol version and a free-form client name."""

    TYPE: ClassVar[str] = "hello"
    protocol: tuple[int, int]
    client: str = ""


@dataclass(frozen=True, slots=True)
class Reset:
    """Starts a new episode of `scenario`; the same seed and options give the same episode."""

    TYPE: ClassVar[str] = "reset"
    scenario: str
    seed: int | None = None
    options: dict[str, OptionValue] = field(default_factory=dict)

    @property
    def many_egos(self) -> bool:
        """It names ``egos`` (1.4) or ``ego_share`` (1.5): a multi-ego episode (§3.1)."""
        options = self.options
        return "egos" in options or "ego_share" in options


@dataclass(frozen=True, slots=True)
class Step:
    """One decision: longitudinal acceleration (m/s^2) and lane change (-1, 0, +1).

    `seq` numbers the steps of an episode from 1; the server answers a repeated `seq` with its
    cached reply instead of advancing the simulation twice.
    """

    TYPE: ClassVar[str] = "step"
    seq: int
    acceleration: float
    lane_change: int = 0


@dataclass(frozen=True, slots=True)
class Command:
    """One ego's decision within a `MultiStep` (since protocol 1.4): as `Step`, for ego `id`."""

    id: str
    acceleration: float
    lane_change: int = 0


@dataclass(frozen=True, slots=True)
class MultiStep:
    """One decision of every running ego (since protocol 1.4), after a reset with ``egos``.

    `commands` has exactly one `Command` per ego of the last `MultiObservation` that had not
    ended; `seq` numbers the steps as `Step` does (a repeat gets the cached reply).
    """

    TYPE: ClassVar[str] = "multi_step"
    seq: int
    commands: tuple[Command, ...]


@dataclass(frozen=True, slots=True)
class Close:
    """Ends the session; the server frees the simulation for the next client."""

    TYPE: ClassVar[str] = "close"


# --------------------------------------------------------------------------- replies


@dataclass(frozen=True, slots=True)
class ScenarioInfo:
    """A scenario the server offers, with its options and their default values.

    `step_length` is the simulator's own time step (s): a decision lasts one or more of them.
    Required since protocol 1.2; None when a 1.0/1.1 server left it out (a client then assumes
    a value, docs/protocol.md §2.2).
    """

    name: str
    description: str
    options: dict[str, OptionValue] = field(default_factory=dict)
    step_length: float | None = None


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One entry of the flat observation vector: name, unit and meaning."""

    name: str
    unit: str
    description: str


@dataclass(frozen=True, slots=True)
class ActionSchema:
    """What a step may ask for: acceleration bounds and the lane-change values."""

    acceleration_min: float
    acceleration_max: float
    lane_change: dict[str, int] = field(default_factory=lambda: {"right": -1, "keep": 0, "left": 1})


@dataclass(frozen=True, slots=True)
class Welcome:
    """The server's answer to `Hello`: versions, scenarios and the two schemas."""

    TYPE: ClassVar[str] = "welcome"
    protocol: tuple[int, int]
    server: str
    backend: str
    backend_version: str
    scenarios: tuple[ScenarioInfo, ...]
    observation_fields: tuple[FieldSpec, ...]
    action: ActionSchema
    sensor_range: float
    max_frame_bytes: int


@dataclass(frozen=True, slots=True)
class Error:
    """A refused request: a stable machine-readable `code` and a human message."""

    TYPE: ClassVar[str] = "error"
    code: str
    message: str


@dataclass(frozen=True, slots=True)
class Bye:
    """Acknowledges `Close`."""

    TYPE: ClassVar[str] = "bye"


# --------------------------------------------------------------------------- observation


@dataclass(frozen=True, slots=True)
class Ego:
    """State of the controlled vehicle after the step.

    `changing_lane` is the direction of the lane change under way (1 left, -1 right, 0 none),
    from the step that started it to the step that completed it: a new lane-change command is
    refused with ``in_progress`` while it is not 0 (since protocol 1.1; 0 from 1.0 servers).
    """

    speed: float
    acceleration: float
    lane: int
    lane_count: int
    position: float
    speed_limit: float
    changing_lane: int = 0


@dataclass(frozen=True, slots=True)
class Neighbour:
    """A surrounding vehicle as seen by the ego's sensors.

    `gap` is the net longitudinal distance, bumper to bumper (negative when the vehicles overlap
    longitudinally, e.g. alongside); `lateral` is the lateral offset of its centre from the ego's
    (positive left). An absent vehicle has ``present=False``, ``gap`` equal to the sensor range,
    ``lateral`` and ``speed`` 0 and an empty id.
    """

    present: bool
    gap: float
    lateral: float
    speed: float
    id: str = ""


@dataclass(frozen=True, slots=True)
class Neighbours:
    """The six neighbours of the paper's Fig. 11: leader and follower in each of three lanes."""

    left_leader: Neighbour
    left_follower: Neighbour
    leader: Neighbour
    follower: Neighbour
    right_leader: Neighbour
    right_follower: Neighbour


@dataclass(frozen=True, slots=True)
class Events:
    """What happened during the step (over all simulation steps of a decision)."""

    collision: bool = False
    collision_with: str = ""
    end_of_road: bool = False
    lane_change_started: bool = False
    lane_change_completed: bool = False
    lane_change_refused: bool = False
    teleported: bool = False
    lane_change_aborted: bool = False
    """A started lane change the simulator gave up (since protocol 1.1)."""
    red_light: bool = False
    """The ego passed the stop line of a traffic light whose state for its link was red
    (since protocol 1.8)."""
    collision_type: str = ""
    """Where the collision happened, a `CollisionType` ("" without one; since protocol 1.8)."""


@dataclass(frozen=True, slots=True)
class AppliedAction:
    """The action as requested and as applied, with the reasons for any difference.

    `acceleration_limited_by` is "" (applied as asked) or an `AccelerationLimit`;
    `lane_change_refused` is "" or a `LaneChangeRefusal`. Both are plain strings on the wire.
    """

    requested_acceleration: float
    requested_lane_change: int
    acceleration: float
    lane_change: int
    acceleration_limited_by: str = ""
    lane_change_refused: str = ""


@dataclass(frozen=True, slots=True)
class LeaderTrip:
    """Trip of the vehicle directly ahead of the ego when it entered: the speed ceiling.

    On a single lane the ego cannot arrive before this vehicle, so its average speed bounds the
    ego's. `arrival_time` and `average_speed` are None if it had not arrived when reported.
    """

    id: str
    depart_time: float
    arrival_time: float | None
    average_speed: float | None


@dataclass(frozen=True, slots=True)
class Traffic:
    """Every vehicle in the simulation but the ego, column by column (since protocol 1.3).

    Index i of every column is one vehicle. `position` is the distance it has driven since it
    entered (an odometer, m); `leader` its leader within the sensor range ("" when none; "ego"
    is the ego), `gap` the net bumper-to-bumper gap to it (the sensor range when none) and
    `leader_speed` its speed (0 when none). Sent only when the reset option ``report_traffic``
    asks for it, on every observation; at most 1,024 vehicles.
    """

    id: tuple[str, ...]
    vehicle_type: tuple[str, ...]
    lane: tuple[int, ...]
    position: tuple[float, ...]
    speed: tuple[float, ...]
    acceleration: tuple[float, ...]
    leader: tuple[str, ...]
    gap: tuple[float, ...]
    leader_speed: tuple[float, ...]

    def __len__(self) -> int:
        return len(self.id)


@dataclass(frozen=True, slots=True)
class Conflict:
    """One conflict of the ego that SUMO's SSM device logged (since protocol 1.3).

    A conflict is an encounter with another vehicle in which a measure crossed its threshold
    (`Safety`). `min_ttc` (s), `max_drac` (m/s^2) and `min_pet` (s) are its extremes, None where
    the measure was never defined; `ttc_below` and `drac_beyond` the seconds it spent beyond the
    TTC and DRAC thresholds, and `ttc_integral` the time-integrated TTC (s^2), the integral of
    (threshold - TTC) over those seconds.
    """

    foe: str
    begin: float
    end: float
    min_ttc: float | None
    max_drac: float | None
    min_pet: float | None
    ttc_below: float
    drac_beyond: float
    ttc_integral: float


@dataclass(frozen=True, slots=True)
class Safety:
    """The ego's surrogate safety measures over the episode, from the simulator (protocol 1.3).

    Set on the last observation when the reset option ``ssm`` asks for it: every conflict, and
    the thresholds that define one (TTC below `ttc_threshold` s, DRAC above `drac_threshold`
    m/s^2, PET below `pet_threshold` s).
    """

    conflicts: tuple[Conflict, ...]
    ttc_threshold: float
    drac_threshold: float
    pet_threshold: float
    ttc_below: float = 0.0
    """Seconds of the episode in which some conflict's TTC was below its threshold (the ego's
    time exposed, TET; conflicts at the same time count once)."""


@dataclass(frozen=True, slots=True)
class Road:
    """The road ahead of the ego along its route (since protocol 1.6): where its lane ends, and
    which lanes lead on.

    A lane "ends" where the ego can no longer drive on in it (and the lanes it leads into)
    without leaving its route: the end of an acceleration lane, a lane drop, a lane that does
    not lead to the ego's exit. Distances are from the ego's front; a lane that goes on for
    `ROAD_RANGE` or farther, or to the end of the route, is reported at `ROAD_RANGE`.
    """

    lane_end: float
    """Metres the ego can still drive in its lane before it must have changed lanes."""
    lanes_to_change: int
    """Lanes to cross to the nearest lane of its road that leads on along its route: positive
    to the left, negative to the right, 0 when its own lane does."""
    left_lane_end: float
    """`lane_end` of the lane to the ego's left; 0 where there is none."""
    right_lane_end: float
    """`lane_end` of the lane to the ego's right; 0 where there is none."""
    stop_line: float = ROAD_RANGE
    """Metres to where the ego must stop now (since protocol 1.7): the next junction on its
    route, when its way there is closed to it (a red light, a yellow one it can stop at, a road
    that must give way to foes approaching with priority, a stop sign not yet stopped at);
    `ROAD_RANGE` when the way is open or no junction is that near. An older server's road has
    none."""
    signal_distance: float = ROAD_RANGE
    """Metres to the stop line of the next traffic light on the ego's route (since protocol
    1.8); `ROAD_RANGE` when there is none that near."""
    signal_state: str = ""
    """The state of the ego's link at that light, a `SignalState` ("" when none)."""
    signal_switch: float = 0.0
    """Seconds until that state changes, by the light's programme as it stands (at most
    `SIGNAL_HORIZON`); 0 when there is no light."""


OPEN_ROAD = Road(ROAD_RANGE, 0, ROAD_RANGE, ROAD_RANGE)
"""A road whose lanes all lead on beyond `ROAD_RANGE` (beside a lane on each side)."""


@dataclass(frozen=True, slots=True)
class Route:
    """The ego's route through the network (since protocol 1.8): on the first and the last
    observation of an episode, so that a result can be traced to the trip."""

    edges: tuple[str, ...]
    """The simulator's ids of the roads of the route, in order (at most `MAX_ROUTE_EDGES`: a
    longer route lists its first ones)."""
    length: float
    """Metres from the start of the route's first road to the end of its last."""
    driven: int
    """How many of the route's roads the ego has entered: 1 at the start, all of them at the
    end of the route."""


@dataclass(frozen=True, slots=True)
class Observation:
    """Recognition state of the ego after a reset (seq 0) or a step (the step's seq).

    `reason` says why an episode ended (an `EndReason`, a plain string on the wire), or is ""
    while it runs. `ceiling` is set on the last observation of an episode, and so is `safety`
    when asked for; `traffic` is on every observation when asked for (protocol 1.3). `road` is
    the road ahead of the ego (protocol 1.6; None from older servers); `route` the ego's route
    on the first and the last observation (protocol 1.8; None on the others, and from a
    simulator without routes).
    """

    TYPE: ClassVar[str] = "observation"
    seq: int
    time: float
    ego: Ego
    neighbours: Neighbours
    events: Events
    action: AppliedAction
    terminated: bool = False
    truncated: bool = False
    reason: str = ""
    ceiling: LeaderTrip | None = None
    safety: Safety | None = None
    traffic: Traffic | None = None
    road: Road | None = None
    route: Route | None = None


@dataclass(frozen=True, slots=True)
class EgoObservation:
    """One ego's part of a `MultiObservation` (since protocol 1.4): an `Observation` without
    the episode's clock, for the ego `id`.

    `terminated`, `truncated` and `reason` are the ego's own: an ego whose drive ended
    (collision, end of road, lost, stopped, lane end, time limit) is reported once so, then
    removed. `road` as in `Observation` (protocol 1.6).
    """

    id: str
    ego: Ego
    neighbours: Neighbours
    events: Events
    action: AppliedAction
    terminated: bool = False
    truncated: bool = False
    reason: str = ""
    road: Road | None = None


@dataclass(frozen=True, slots=True)
class MultiObservation:
    """Every ego after a reset with ``egos`` (seq 0) or a `MultiStep` (since protocol 1.4).

    `egos` lists each ego still driving before this step, in a stable order (the order egos
    entered). The episode goes on while one of them runs: `terminated` once none is left and
    none will come, `truncated` at the time limit (every running ego truncated too), and
    `reason` then says why (`EndReason`). `traffic` as in `Observation`, when asked for.
    """

    TYPE: ClassVar[str] = "multi_observation"
    seq: int
    time: float
    egos: tuple[EgoObservation, ...]
    terminated: bool = False
    truncated: bool = False
    reason: str = ""
    traffic: Traffic | None = None


def road_ahead(obs: Observation) -> Road:
    """`obs.road`, or for an observation without one (from a server older than 1.6) the open
    road: every lane leads on beyond `ROAD_RANGE`, a lane on a side where the road has one."""
    road = obs.road
    if road is not None:
        return road
    ego = obs.ego
    if ego.lane > 0 and ego.lane < ego.lane_count - 1:
        return OPEN_ROAD
    left = ROAD_RANGE if ego.lane < ego.lane_count - 1 else 0.0
    right = ROAD_RANGE if ego.lane > 0 else 0.0
    return Road(ROAD_RANGE, 0, left, right)


Request = Hello | Reset | Step | MultiStep | Close
Reply = Welcome | Observation | MultiObservation | Error | Bye
Message = Request | Reply

REQUEST_TYPES: tuple[type[Request], ...] = (Hello, Reset, Step, MultiStep, Close)
REPLY_TYPES: tuple[type[Reply], ...] = (Welcome, Observation, MultiObservation, Error, Bye)
