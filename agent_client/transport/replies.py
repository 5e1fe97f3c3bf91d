"""Every reply judged against docs/protocol.md: the welcome once, then each reply against the
request it answers.

The one place where the client checks what a server says, for `RemoteEnv` and for the
conformance kit alike, so that the kit fails a server with the words the client would raise. A
broken rule is an `InvalidReply` that names the field, the value and the rule (with its section
of protocol.md). What the codec already guarantees (types, finite numbers, int64, string
lengths, string keys) is not checked again.

A multi-ego episode (since 1.4: a reset naming ``egos``, then `MultiStep`s) is judged frame by
frame: each `EgoObservation` by the rules of an observation (built with the frame's seq and
time, against that ego's previous observation), the frame by §3.1's (the ids, the egos' ends).

Rules a newer minor version may extend (the values of `reason`, `acceleration_limited_by`,
`lane_change_refused` and the error codes) accept unknown values from a server of a newer minor
version; rules added in 1.2 (a `step_length` for every scenario, the content of the first
observation) apply to servers of 1.2 and later.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

from agent_client.errors import InvalidReply
from protocol.errors import ErrorCode
from protocol.messages import (
    MAX_ROUTE_EDGES,
    ROAD_RANGE,
    SIGNAL_HORIZON,
    AccelerationLimit,
    AppliedAction,
    Bye,
    Close,
    CollisionType,
    EgoObservation,
    EndReason,
    Error,
    Events,
    Hello,
    LaneChangeRefusal,
    MultiObservation,
    MultiStep,
    Observation,
    Reply,
    Request,
    Reset,
    Road,
    SignalState,
    Step,
    Traffic,
    Welcome,
)
from protocol.schema import NEIGHBOUR_SLOTS, Flattener
from protocol.version import PROTOCOL_VERSION, format_version

TOLERANCE = 1e-6
"""Relative slack on floats a server computes (a mean over simulation steps, float32 values)."""
LEGACY_STEP_LENGTH = 0.1
"""What a 1.0/1.1 server that announced no `step_length` is assumed to run at when its scenario
has no `decision_interval` default either (the value our 1.0/1.1 servers announced)."""

WELL_KNOWN_OPTIONS: dict[str, type] = {
    "decision_interval": float,
    "max_episode_time": float,
    "report_ceiling": bool,
    "ego_driver": str,
    "ssm": bool,
    "report_traffic": bool,
    "egos": int,
}
"""Options the client sets when a scenario offers them (protocol.md §2.3), with their types."""

TERMINAL_REASONS = frozenset(r.value for r in EndReason if r.terminates)
TRUNCATION_REASONS = frozenset(r.value for r in EndReason if not r.terminates)
ACCELERATION_LIMITS = frozenset(a.value for a in AccelerationLimit)
LANE_CHANGE_REFUSALS = frozenset(r.value for r in LaneChangeRefusal)
SIGNAL_STATES = frozenset(s.value for s in SignalState)
COLLISION_TYPES = frozenset(c.value for c in CollisionType)
ERROR_CODES = frozenset(code.value for code in ErrorCode)
_ANSWERS: dict[type, tuple[type, ...]] = {
    Hello: (Welcome, Error),
    Reset: (Observation, Error),
    Step: (Observation, Error),
    MultiStep: (MultiObservation, Error),
    Close: (Bye, Error),
}
_MANY_EGOS = (MultiObservation, Error)
"""The answers to a reset that names ``egos`` (§3.1)."""
_EPISODE_ENDERS = frozenset({ErrorCode.INSERTION_FAILED.value, ErrorCode.SIMULATOR_ERROR.value})


# --------------------------------------------------------------------------- the welcome


def check_welcome(
    welcome: Welcome, source: str = "", scenario: str | None = None
) -> tuple[Welcome, list[str]]:
    """The welcome with every scenario's step length known, and notes on what was assumed.

    Raises `InvalidReply` for the first broken rule: of the handshake, and of the scenarios
    (only `scenario`'s when given).
    """
    for problem in (*handshake_problems(welcome, source), *scenario_problems(welcome, source)):
        if (
            scenario is None
            or not problem.field.startswith("welcome.scenarios[")
            or (_scenario_of(welcome, problem.field) == scenario)
        ):
            raise problem
    return with_step_lengths(welcome, source)


def handshake_problems(welcome: Welcome, source: str = "") -> list[InvalidReply]:
    """Broken rules of the welcome outside its scenarios' options (§2.2, §3, §4.6)."""
    problems: list[InvalidReply] = []
    rule = _Rules(source, problems)
    if welcome.protocol[0] != PROTOCOL_VERSION[0]:
        rule(
            "welcome.protocol",
            format_version(welcome.protocol),
            f"major version {PROTOCOL_VERSION[0]}: a server refuses a hello of another major "
            "version with version_mismatch (§3 Handshake)",
        )
    if not welcome.scenarios:
        rule("welcome.scenarios", [], "at least one scenario (§2.2)")
    seen: set[str] = set()
    for i, info in enumerate(welcome.scenarios):
        if not info.name or info.name in seen:
            rule(f"welcome.scenarios[{i}].name", info.name, "a non-empty, unique name (§2.2)")
        seen.add(info.name)
    names = [f.name for f in welcome.observation_fields]
    if not names:
        rule("welcome.observation_fields", [], "at least one field (§4.6)")
    for i, name in enumerate(names):
        if name in names[:i]:
            rule(f"welcome.observation_fields[{i}].name", name, "each field once (§4.6)")
    try:
        Flattener(welcome.observation_fields)
    except ValueError as exc:
        rule("welcome.observation_fields", None, f"{exc} (§4.6)")
    _action_problems(welcome, rule)
    if not welcome.sensor_range > 0:
        rule("welcome.sensor_range", welcome.sensor_range, "> 0 m (§2.2)")
    if not welcome.max_frame_bytes > 0:
        rule("welcome.max_frame_bytes", welcome.max_frame_bytes, "> 0 (§1)")
    return problems


def _action_problems(welcome: Welcome, rule: _Rules) -> None:
    action = welcome.action
    if not action.acceleration_min < 0 < action.acceleration_max:
        rule(
            "welcome.action",
            f"[{action.acceleration_min:g}, {action.acceleration_max:g}]",
            "acceleration_min < 0 < acceleration_max (§2.2)",
        )
    if action.lane_change != {"right": -1, "keep": 0, "left": 1}:
        rule(
            "welcome.action.lane_change",
            action.lane_change,
            "exactly {right: -1, keep: 0, left: 1} (§2.2)",
        )


def scenario_problems(welcome: Welcome, source: str = "") -> list[InvalidReply]:
    """Broken rules of the scenarios: step length, option defaults (§2.2, §2.3)."""
    problems: list[InvalidReply] = []
    rule = _Rules(source, problems)
    for i, info in enumerate(welcome.scenarios):
        where = f"welcome.scenarios[{i}]"
        step = info.step_length
        if step is None and welcome.protocol >= (1, 2):
            rule(f"{where}.step_length", None, "required since protocol 1.2: s > 0 (§2.2)")
        elif step is not None and not (math.isfinite(step) and step > 0):
            rule(f"{where}.step_length", step, "the simulation step, a finite number > 0 s (§2.2)")
        for name, kind in WELL_KNOWN_OPTIONS.items():
            if name in info.options:
                _option_problems(f"{where}.options.{name}", info.options[name], kind, rule)
        interval = info.options.get("decision_interval")
        if isinstance(interval, float) and interval > 0 and step and step > 0:
            steps = round(interval / step)
            if steps < 1 or abs(steps * step - interval) > TOLERANCE * max(1.0, interval):
                rule(
                    f"{where}.options.decision_interval",
                    interval,
                    f"a whole number of simulation steps of {step:g} s (§2.3)",
                )
    return problems


def _option_problems(field: str, default: object, kind: type, rule: _Rules) -> None:
    if kind is float and type(default) is int:
        rule(
            field, default, "a float option: its default is a msgpack float (300.0, not 300), §2.3"
        )
    elif type(default) is not kind:
        rule(field, default, f"{'an' if kind is int else 'a'} {kind.__name__} option (§2.3)")
    elif kind is float and not default > 0:  # type: ignore[operator]
        rule(field, default, "> 0 s (§2.3)")
    elif kind is int and not default >= 1:  # type: ignore[operator]
        rule(field, default, ">= 1 (§2.3)")


def with_step_lengths(welcome: Welcome, source: str = "") -> tuple[Welcome, list[str]]:
    """The welcome with every missing step length assumed (a 1.0/1.1 server), and a note for
    each: its scenario's float `decision_interval` default, else `LEGACY_STEP_LENGTH`."""
    notes, scenarios = [], []
    for info in welcome.scenarios:
        if info.step_length is None:
            interval = info.options.get("decision_interval")
            assumed = interval if type(interval) is float and interval > 0 else LEGACY_STEP_LENGTH
            notes.append(
                f"{source + ': ' if source else ''}scenario {info.name} announces no step_length "
                f"(protocol {format_version(welcome.protocol)}): assuming {assumed:g} s; jerk "
                "figures are measured at that step"
            )
            info = replace(info, step_length=assumed)
        scenarios.append(info)
    return replace(welcome, scenarios=tuple(scenarios)), notes


def _scenario_of(welcome: Welcome, field: str) -> str | None:
    index = field.removeprefix("welcome.scenarios[").split("]", 1)[0]
    return welcome.scenarios[int(index)].name if index.isdigit() else None


# --------------------------------------------------------------------------- every reply


class ReplyChecker:
    """Judges the replies of one session, each against the request it answers.

    Keeps the episode's last observation: a step's reply is checked against it (time goes on,
    lane changes start from its lane, a retried step gets the cached reply). In a multi-ego
    episode it keeps the last frame and each of its egos' observations instead.
    """

    def __init__(self, welcome: Welcome, source: str = "") -> None:
        self.welcome = welcome
        self.source = source
        self.newer = welcome.protocol[1] > PROTOCOL_VERSION[1]
        """The server speaks a newer minor version: values unknown to us may be its additions."""
        self.last: Observation | None = None
        """The last observation of the running episode (None between episodes)."""
        self.last_frame: MultiObservation | None = None
        """The last frame of the running multi-ego episode (None between episodes and in a
        one-ego episode)."""
        self.last_egos: dict[str, Observation] = {}
        """Each ego of `last_frame` by id, as an `Observation` (`ego_observation`): what its
        next observation is judged against."""
        self.joins = False
        """The running multi-ego episode's reset named ``ego_share``: egos may join (1.5)."""
        self.seen: set[str] = set()
        """Every ego of the running multi-ego episode so far (a joining ego is a new one)."""

    def check(self, request: Request | None, reply: Reply) -> Reply:
        """`reply` if it is a valid answer to `request` (None: unknown); else `InvalidReply`."""
        for problem in self.problems(request, reply):
            raise problem
        if isinstance(request, Hello) or (
            isinstance(reply, Error) and reply.code in _EPISODE_ENDERS
        ):
            self._forget()
        elif isinstance(reply, Observation) and isinstance(request, Reset | Step):
            self._forget()
            self.last = reply
        elif isinstance(reply, MultiObservation) and isinstance(request, Reset | MultiStep):
            joins, seen = self.joins, self.seen
            self._forget()
            if isinstance(request, Reset):
                joins, seen = "ego_share" in request.options, set()
            self.last_frame = reply
            self.last_egos = {ego.id: ego_observation(reply, ego) for ego in reply.egos}
            self.joins, self.seen = joins, seen | self.last_egos.keys()
        return reply

    def _forget(self) -> None:
        """No episode runs (or a new one starts)."""
        self.last, self.last_frame, self.last_egos = None, None, {}
        self.joins, self.seen = False, set()

    def problems(self, request: Request | None, reply: Reply) -> list[InvalidReply]:
        """Every broken rule of `reply` as the answer to `request` (none: valid)."""
        problems: list[InvalidReply] = []
        rule = _Rules(self.source, problems)
        many = isinstance(request, Reset) and request.many_egos
        expected = _MANY_EGOS if many else _ANSWERS.get(type(request), ())
        if expected and not isinstance(reply, expected):
            names = " or ".join(getattr(kind, "TYPE", "?") for kind in expected)
            asked = "reset that names egos" if many else getattr(request, "TYPE", "request")
            where = "§3.1" if many or isinstance(request, MultiStep) else "§2.2"
            rule("reply.type", reply.TYPE, f"a {asked} is answered by {names} ({where})")
        elif isinstance(reply, Error):
            if reply.code not in ERROR_CODES and not self.newer:
                rule("error.code", reply.code, "one of the codes of §5")
        elif isinstance(reply, Observation):
            last = self.last if isinstance(request, Step) else None
            _ObservationRules(self, rule, reply, request, last).run()
        elif isinstance(reply, MultiObservation):
            _FrameRules(self, rule, reply, request).run()
        return problems


def ego_observation(frame: MultiObservation, ego: EgoObservation) -> Observation:
    """One ego of a multi-ego frame as an `Observation`: the frame's seq, time and traffic with
    the ego's own state, events, action and end (what rewards and drivers take)."""
    return Observation(
        frame.seq, frame.time, ego.ego, ego.neighbours, ego.events, ego.action,
        ego.terminated, ego.truncated, ego.reason, traffic=frame.traffic, road=ego.road,
    )  # fmt: skip


class _Rules:
    """Collects broken rules as `InvalidReply`s of one source."""

    def __init__(self, source: str, into: list[InvalidReply]) -> None:
        self.source = source
        self.into = into

    def __call__(self, field: str, value: object, rule: str) -> None:
        self.into.append(InvalidReply(field, value, rule, self.source))


class _ObservationRules:
    """The rules of one observation (§3, §4), given the request it answers."""

    def __init__(
        self,
        checker: ReplyChecker,
        rule: _Rules,
        obs: Observation,
        request: Request | None,
        last: Observation | None,
        where: str = "observation",
        ends: str = "ends the episode (§4.1)",
    ) -> None:
        """`request` is what `obs` answers (for an ego of a frame: a `Step` of its command, or
        the reset); `last` the observation the step was decided on; `where` names the fields
        (``observation``, ``multi_observation.egos[2]``); `ends` says what a collision ends."""
        self.welcome = checker.welcome
        self.newer = checker.newer
        self.rule = rule
        self.obs = obs
        self.request = request
        self.last = last
        self.where = where
        self.ends = ends

    def run(self) -> None:
        obs, request = self.obs, self.request
        last = self.last
        if isinstance(request, Step) and last is not None and request.seq == last.seq > 0:
            if obs != last:  # a retry: nothing else to judge
                self.rule(
                    self.where,
                    None,
                    f"a retry of step {request.seq} (the same seq) gets the cached reply of its "
                    "first answer, unchanged (§3 Steps)",
                )
            return
        self.sequence()
        self.body()
        self.ceiling()
        self.safety()
        self.route()
        _traffic_problems(obs.traffic, self.where, self.rule)

    def body(self) -> None:
        """The rules of the ego's own observation: also each ego's of a multi-ego frame."""
        request = self.request
        self.ending()
        self.ego()
        self.neighbours()
        self.road()
        self.events()
        if isinstance(request, Step):
            self.action(request)
        elif isinstance(request, Reset) and self.welcome.protocol >= (1, 2):
            self.first()

    def sequence(self) -> None:
        obs, request = self.obs, self.request
        if isinstance(request, Reset) and obs.seq != 0:
            self.rule(f"{self.where}.seq", obs.seq, "0 in the reply to a reset (§4.1)")
        elif isinstance(request, Step) and obs.seq != request.seq:
            self.rule(
                f"{self.where}.seq",
                obs.seq,
                f"{request.seq} in the reply to step {request.seq} (§3 Steps)",
            )
        last = self.last
        if last is not None and not obs.time > last.time:
            self.rule(
                f"{self.where}.time",
                obs.time,
                f"later than the previous observation's {last.time:g} s: a step advances the "
                "simulation (§4.1)",
            )

    def ending(self) -> None:
        obs = self.obs
        if obs.terminated and obs.truncated:
            self.rule(f"{self.where}.truncated", True, "never true with terminated (§4.1)")
        elif isinstance(self.request, Reset) and (obs.terminated or obs.truncated):
            self.rule(
                f"{self.where}.terminated" if obs.terminated else f"{self.where}.truncated",
                True,
                "false at seq 0: an episode that cannot start is refused with insertion_failed "
                "or simulator_error (§3 Reset)",
            )
        elif obs.terminated:
            self._reason(TERMINAL_REASONS, "a terminated episode's reason")
        elif obs.truncated:
            self._reason(TRUNCATION_REASONS, "a truncated episode's reason")
        elif obs.reason:
            self.rule(f"{self.where}.reason", obs.reason, '"" while the episode runs (§4.1)')

    def _reason(self, allowed: frozenset[str], what: str) -> None:
        reason = self.obs.reason
        if not _reason_ok(reason, allowed, self.newer):
            self.rule(f"{self.where}.reason", reason, f"{what}: {_one_of(allowed)} (§4.1)")

    def ego(self) -> None:
        ego = self.obs.ego
        driven = self.obs.action.acceleration_limited_by == AccelerationLimit.SIMULATOR.value
        if ego.speed < 0 and not driven:  # the simulator's own driver may reverse a little
            self.rule(f"{self.where}.ego.speed", ego.speed, ">= 0 m/s (§3 Action semantics)")
        if ego.lane_count < 1:
            self.rule(f"{self.where}.ego.lane_count", ego.lane_count, ">= 1 (§4.2)")
        elif not 0 <= ego.lane < ego.lane_count:
            self.rule(
                f"{self.where}.ego.lane",
                ego.lane,
                f"a lane of the road at the ego, 0..{ego.lane_count - 1} with lane_count "
                f"{ego.lane_count} (§4.2)",
            )
        if ego.changing_lane not in (-1, 0, 1):
            self.rule(f"{self.where}.ego.changing_lane", ego.changing_lane, "-1, 0 or 1 (§4.2)")
        if not ego.speed_limit > 0:
            self.rule(f"{self.where}.ego.speed_limit", ego.speed_limit, "> 0 m/s (§4.2)")

    def road(self) -> None:
        """The road ahead (§4.9, since 1.6): distances within [0, ROAD_RANGE] (the stop line's
        too, since 1.7), none beside the ego where there is no lane, a lane to change to that
        exists."""
        road = self.obs.road
        if road is None:
            return
        lane, lanes = self.obs.ego.lane, self.obs.ego.lane_count
        where = f"{self.where}.road"
        top = ROAD_RANGE * (1 + TOLERANCE)
        for name in ("lane_end", "left_lane_end", "right_lane_end", "stop_line"):
            value = getattr(road, name)
            if not 0 <= value <= top:
                self.rule(f"{where}.{name}", value, f"within [0, {ROAD_RANGE:g}] m (§4.9)")
        for name, value, side, missing in (
            ("left_lane_end", road.left_lane_end, "left", lane >= lanes - 1),
            ("right_lane_end", road.right_lane_end, "right", lane <= 0),
        ):
            if missing and value != 0:
                self.rule(
                    f"{where}.{name}",
                    value,
                    f"0: there is no lane to the {side} of lane {lane} of {lanes} (§4.9)",
                )
        if not -lane <= road.lanes_to_change <= lanes - 1 - lane:
            self.rule(
                f"{where}.lanes_to_change",
                road.lanes_to_change,
                f"a lane of the road from lane {lane} of {lanes}: within "
                f"{-lane}..{lanes - 1 - lane} (§4.9)",
            )
        self._signal(road, where, top)

    def _signal(self, road: Road, where: str, top: float) -> None:
        """The next traffic light (§4.9, since 1.8): a known state (or a newer server's), a
        distance within the road's range and the seconds to its change within the horizon;
        none at all ("") is the range and 0 s."""
        state = road.signal_state
        if state not in SIGNAL_STATES and not self.newer:
            self.rule(f"{where}.signal_state", state, f"one of {_one_of(SIGNAL_STATES)} (§4.9)")
        if not 0 <= road.signal_distance <= top:
            self.rule(
                f"{where}.signal_distance",
                road.signal_distance,
                f"within [0, {ROAD_RANGE:g}] m (§4.9)",
            )
        if not 0 <= road.signal_switch <= SIGNAL_HORIZON * (1 + TOLERANCE):
            self.rule(
                f"{where}.signal_switch",
                road.signal_switch,
                f"within [0, {SIGNAL_HORIZON:g}] s (§4.9)",
            )
        if not state and (road.signal_distance < ROAD_RANGE or road.signal_switch):
            self.rule(
                f"{where}.signal_state",
                state,
                f"a state where a light is {road.signal_distance:g} m ahead (§4.9)",
            )

    def neighbours(self) -> None:
        obs, sensed = self.obs, self.welcome.sensor_range
        lane, lanes = obs.ego.lane, obs.ego.lane_count
        for slot in NEIGHBOUR_SLOTS:
            where = f"{self.where}.neighbours.{slot}"
            other = getattr(obs.neighbours, slot)
            if not other.present:
                if (other.gap, other.lateral, other.speed, other.id) == (sensed, 0.0, 0.0, ""):
                    continue
                absent = {"gap": sensed, "lateral": 0.0, "speed": 0.0, "id": ""}
                for key, value in absent.items():
                    if getattr(other, key) != value:
                        self.rule(
                            f"{where}.{key}",
                            getattr(other, key),
                            f"{_show(value)} for an absent neighbour (§4.3)",
                        )
                continue
            if other.gap > sensed * (1 + TOLERANCE):
                self.rule(
                    f"{where}.gap", other.gap, f"<= sensor_range {sensed:g} m if present (§4.3)"
                )
            side = slot.split("_")[0]
            if (side == "left" and lane >= lanes - 1) or (side == "right" and lane <= 0):
                self.rule(
                    f"{where}.present",
                    True,
                    f"false: there is no lane to the {side} of lane {lane} of {lanes} (§4.3)",
                )

    def events(self) -> None:
        obs, events = self.obs, self.obs.events
        ended = obs.terminated or obs.truncated
        if events.collision_with and not events.collision:
            self.rule(
                f"{self.where}.events.collision_with",
                events.collision_with,
                '"" unless events.collision (§4.4)',
            )
        for flag, reason in (("collision", "collision"), ("end_of_road", "end_of_road")):
            happened = getattr(events, flag)
            if happened and not ended:
                self.rule(f"{self.where}.events.{flag}", True, self.ends)
            if obs.reason == reason and not happened:
                self.rule(
                    f"{self.where}.reason", reason, f"comes with events.{flag} true (§4.1, §4.4)"
                )
        if obs.reason == "red_light" and not events.red_light:
            self.rule(f"{self.where}.reason", obs.reason, "comes with events.red_light (§4.4)")
        kind = events.collision_type
        if kind and not events.collision:
            self.rule(
                f"{self.where}.events.collision_type", kind, '"" unless events.collision (§4.4)'
            )
        elif kind and kind not in COLLISION_TYPES and not self.newer:
            self.rule(
                f"{self.where}.events.collision_type",
                kind,
                f'"" or one of {_one_of(COLLISION_TYPES)} (§4.4)',
            )

    def route(self) -> None:
        """The ego's route (§4.1, since 1.8): on the first and the last observation only, a
        length that is not negative, the roads driven within the route."""
        obs, route = self.obs, self.obs.route
        if route is None:
            return
        where = f"{self.where}.route"
        if obs.seq > 0 and not (obs.terminated or obs.truncated):
            self.rule(where, None, "nil but on the first and the last observation (§4.1)")
        if not route.length >= 0:
            self.rule(f"{where}.length", route.length, ">= 0 m (§4.1)")
        if route.driven < 0 or (
            len(route.edges) < MAX_ROUTE_EDGES and route.driven > len(route.edges)
        ):
            self.rule(
                f"{where}.driven",
                route.driven,
                f"within 0..{len(route.edges)}, the roads of the route (§4.1)",
            )

    def action(self, step: Step) -> None:
        action, welcome = self.obs.action, self.welcome
        low, high = welcome.action.acceleration_min, welcome.action.acceleration_max
        where = f"{self.where}.action"
        if not _close(action.requested_acceleration, step.acceleration):
            self.rule(
                f"{where}.requested_acceleration",
                action.requested_acceleration,
                f"{step.acceleration:g}, as the step asked (§4.4)",
            )
        if action.requested_lane_change != step.lane_change:
            self.rule(
                f"{where}.requested_lane_change",
                action.requested_lane_change,
                f"{step.lane_change}, as the step asked (§4.4)",
            )
        slack = TOLERANCE * max(1.0, abs(low), abs(high))
        driven = action.acceleration_limited_by == AccelerationLimit.SIMULATOR.value
        if not driven and not low - slack <= action.acceleration <= high + slack:
            self.rule(
                f"{where}.acceleration",
                action.acceleration,
                f"within the announced bounds [{low:g}, {high:g}] m/s^2 (§3 Action semantics)",
            )
        self._limit(action, step, low, high)
        self._lane_change(action, step)

    def _limit(self, action: AppliedAction, step: Step, low: float, high: float) -> None:
        why, where = action.acceleration_limited_by, f"{self.where}.action.acceleration_limited_by"
        if why and why not in ACCELERATION_LIMITS and not self.newer:
            self.rule(where, why, f'"" or {_one_of(ACCELERATION_LIMITS)} (§4.4)')
        elif not why and not low <= step.acceleration <= high:
            self.rule(
                where, why, f"names the limit: {step.acceleration:g} is outside the bounds (§4.4)"
            )
        elif not why and not _close(action.acceleration, step.acceleration):
            self.rule(
                f"{self.where}.action.acceleration",
                action.acceleration,
                f"{step.acceleration:g}, as asked: acceleration_limited_by is empty (§4.4)",
            )

    def _lane_change(self, action: AppliedAction, step: Step) -> None:
        where, refused = f"{self.where}.action", action.lane_change_refused
        asked, applied = step.lane_change, action.lane_change
        if applied not in (0, asked):
            self.rule(f"{where}.lane_change", applied, f"0 (refused) or {asked}, as asked (§4.4)")
        if refused and refused not in LANE_CHANGE_REFUSALS and not self.newer:
            self.rule(
                f"{where}.lane_change_refused", refused, f'"" or {_one_of(LANE_CHANGE_REFUSALS)}'
            )
        if refused and (applied or not asked):
            self.rule(
                f"{where}.lane_change_refused",
                refused,
                '"" unless a lane change was asked for and not applied (§4.4)',
            )
        elif asked and not applied and not refused:
            self.rule(f"{where}.lane_change_refused", "", "names why the lane change was refused")
        events = self.obs.events
        if events.lane_change_refused != bool(refused):
            self.rule(
                f"{self.where}.events.lane_change_refused",
                events.lane_change_refused,
                f"{bool(refused)}: true exactly when action.lane_change_refused is set (§4.4)",
            )
        if events.lane_change_started != bool(applied):
            self.rule(
                f"{self.where}.events.lane_change_started",
                events.lane_change_started,
                f"{bool(applied)}: true exactly when the applied lane_change is not 0 (§4.4)",
            )
        if self.last is not None:
            self._lanes_before(applied, asked, refused, self.last)

    def _lanes_before(self, applied: int, asked: int, refused: str, last: Observation) -> None:
        """The lane change judged on the lane the decision was taken in (the last observation)."""
        lane, lanes, where = last.ego.lane, last.ego.lane_count, f"{self.where}.action"
        if applied and not 0 <= lane + applied < lanes:
            self.rule(
                f"{where}.lane_change",
                applied,
                f"refused (no_lane): there is no lane {lane + applied} beside lane {lane} of "
                f"{lanes} (§3 Action semantics)",
            )
        if refused == "no_lane" and 0 <= lane + asked < lanes:
            self.rule(
                f"{where}.lane_change_refused",
                refused,
                f"lane {lane + asked} exists beside lane {lane} of {lanes} (§3 Action semantics)",
            )
        if self.welcome.protocol < (1, 1):
            return  # no changing_lane before 1.1
        under_way = last.ego.changing_lane
        if refused == "in_progress" and not under_way:
            self.rule(
                f"{where}.lane_change_refused",
                refused,
                "only while a lane change is under way: the last ego.changing_lane was 0 (§4.2)",
            )
        if applied and under_way:
            self.rule(
                f"{where}.lane_change",
                applied,
                f"0 (in_progress): a lane change was under way (changing_lane {under_way}) (§4.2)",
            )

    def first(self, when: str = "at seq 0 (§4.4)") -> None:
        """Seq 0 (since 1.2), or an ego that joins (1.5): nothing has happened and nothing was
        decided yet."""
        obs = self.obs
        if obs.events != Events():
            self.rule(f"{self.where}.events", None, f"all false {when}")
        if obs.action != AppliedAction(0.0, 0, 0.0, 0):
            self.rule(f"{self.where}.action", None, f'zeros and "" {when}')
        if obs.ego.changing_lane:
            self.rule(f"{self.where}.ego.changing_lane", obs.ego.changing_lane, f"0 {when}")

    def ceiling(self) -> None:
        obs, trip = self.obs, self.obs.ceiling
        if trip is None:
            return
        if not (obs.terminated or obs.truncated):
            self.rule(f"{self.where}.ceiling", trip.id, "nil until the last observation (§4.5)")
            return
        if (trip.arrival_time is None) != (trip.average_speed is None):
            self.rule(
                f"{self.where}.ceiling.average_speed",
                trip.average_speed,
                "nil exactly when arrival_time is nil (§4.5)",
            )
        if trip.arrival_time is not None and trip.arrival_time < trip.depart_time:
            self.rule(
                f"{self.where}.ceiling.arrival_time",
                trip.arrival_time,
                f"not before depart_time {trip.depart_time:g} s (§4.5)",
            )
        if trip.average_speed is not None and not trip.average_speed > 0:
            self.rule(f"{self.where}.ceiling.average_speed", trip.average_speed, "> 0 m/s (§4.5)")

    def safety(self) -> None:
        obs, safety = self.obs, self.obs.safety
        if safety is None:
            return
        if not (obs.terminated or obs.truncated):
            self.rule(f"{self.where}.safety", None, "nil until the last observation (§4.7)")
            return
        thresholds = (safety.ttc_threshold, safety.drac_threshold, safety.pet_threshold)
        if min(thresholds) <= 0 or safety.ttc_below < 0:
            self.rule(f"{self.where}.safety", min(*thresholds, safety.ttc_below), "> 0 (§4.7)")
        for i, conflict in enumerate(safety.conflicts):
            if conflict.end < conflict.begin:
                self.rule(
                    f"{self.where}.safety.conflicts[{i}].end",
                    conflict.end,
                    f"not before begin {conflict.begin:g} s (§4.7)",
                )
            spent = (conflict.ttc_below, conflict.drac_beyond, conflict.ttc_integral)
            if min(spent) < 0:
                self.rule(f"{self.where}.safety.conflicts[{i}]", min(spent), ">= 0 (§4.7)")


class _FrameRules:
    """The rules of one multi-ego frame (§3.1), given the request it answers: its seq and time,
    the egos it lists, its end; each ego's observation by `_ObservationRules`."""

    WHERE = "multi_observation"

    def __init__(
        self, checker: ReplyChecker, rule: _Rules, frame: MultiObservation, request: Request | None
    ) -> None:
        self.checker = checker
        self.rule = rule
        self.frame = frame
        self.request = request
        self.last = checker.last_frame if isinstance(request, MultiStep) else None

    def run(self) -> None:
        frame, request, last = self.frame, self.request, self.last
        if isinstance(request, MultiStep) and last is not None and request.seq == last.seq > 0:
            if frame != last:  # a retry: nothing else to judge
                self.rule(
                    self.WHERE,
                    None,
                    f"a retry of multi_step {request.seq} (the same seq) gets the cached reply of "
                    "its first answer, unchanged (§3 Steps, §3.1)",
                )
            return
        self.sequence()
        self.ids()
        self.ending()
        self.egos()
        _traffic_problems(frame.traffic, self.WHERE, self.rule)

    def sequence(self) -> None:
        frame, request, last = self.frame, self.request, self.last
        if isinstance(request, Reset) and frame.seq != 0:
            self.rule(f"{self.WHERE}.seq", frame.seq, "0 in the reply to a reset (§4.1)")
        elif isinstance(request, MultiStep) and frame.seq != request.seq:
            self.rule(
                f"{self.WHERE}.seq",
                frame.seq,
                f"{request.seq} in the reply to multi_step {request.seq} (§3 Steps)",
            )
        if last is not None and not frame.time > last.time:
            self.rule(
                f"{self.WHERE}.time",
                frame.time,
                f"later than the previous frame's {last.time:g} s: a step advances the "
                "simulation (§4.1)",
            )

    def ids(self) -> None:
        """Each ego once; at seq 0 as many as asked for, afterwards exactly those still driving
        before the step, in the stable order, then (``ego_share``) any that join."""
        ids = [ego.id for ego in self.frame.egos]
        for i, ego_id in enumerate(ids):
            if ego_id in ids[:i]:
                self.rule(f"{self.WHERE}.egos[{i}].id", ego_id, "each ego once in a frame (§3.1)")
        request, where = self.request, f"{self.WHERE}.egos"
        if isinstance(request, Reset):
            asked = request.options.get("egos")
            if isinstance(asked, int) and not isinstance(asked, bool) and len(ids) != asked:
                self.rule(where, ids, f"{asked} egos at seq 0 of a reset with egos {asked} (§3.1)")
            return
        if not isinstance(request, MultiStep):
            return
        last = self.last
        running = (
            [e.id for e in last.egos if not _over(e)]
            if last is not None
            else [c.id for c in request.commands]
        )
        checker = self.checker
        head, joined = ids[: len(running)], ids[len(running) :]
        if set(head) != set(running) or (joined and not checker.joins):
            then = ", then those that join (ego_share)" if checker.joins else ""
            self.rule(
                where,
                ids,
                f"exactly the egos driving before the step, {running}{then}: an ego that ended "
                "is listed once with its end, then no more (§3.1)",
            )
            return
        if head != running:
            self.rule(where, ids, f"the stable order of the previous frame, {running} (§3.1)")
        for i, ego in enumerate(self.frame.egos[len(running) :], start=len(running)):
            if ego.id in checker.seen:
                self.rule(f"{where}[{i}].id", ego.id, "a joining ego is new to the episode (§3.1)")
            elif _over(ego):
                self.rule(
                    f"{where}[{i}].terminated" if ego.terminated else f"{where}[{i}].truncated",
                    True,
                    "false: an ego that joins drives (§3.1)",
                )

    def ending(self) -> None:
        """The frame's flags and reason against its egos' ends (§3.1)."""
        frame, where = self.frame, self.WHERE
        if frame.terminated and frame.truncated:
            self.rule(f"{where}.truncated", True, "never true with terminated (§4.1)")
        elif isinstance(self.request, Reset):  # each ego's own rules judge it at seq 0 too
            if frame.terminated or frame.truncated:
                self.rule(
                    f"{where}.terminated" if frame.terminated else f"{where}.truncated",
                    True,
                    "false at seq 0: an episode that cannot start is refused with "
                    "insertion_failed or simulator_error (§3 Reset)",
                )
        elif frame.truncated:
            self._truncated()
        elif any(ego.truncated for ego in frame.egos):
            i = next(i for i, ego in enumerate(frame.egos) if ego.truncated)
            self.rule(
                f"{where}.truncated",
                False,
                f"true: egos[{i}] ({frame.egos[i].id}) is truncated, and the time limit "
                "truncates the frame with it (§3.1)",
            )
        else:
            self._terminated()

    def _truncated(self) -> None:
        frame, where = self.frame, self.WHERE
        if not _reason_ok(frame.reason, TRUNCATION_REASONS, self.checker.newer):
            self.rule(
                f"{where}.reason",
                frame.reason,
                f"a truncated episode's reason: {_one_of(TRUNCATION_REASONS)} (§4.1)",
            )
        for i, ego in enumerate(frame.egos):
            if not _over(ego):
                self.rule(
                    f"{where}.egos[{i}].truncated",
                    False,
                    "true at the time limit: every ego still driving is truncated with the "
                    "frame (§3.1)",
                )

    def _terminated(self) -> None:
        frame, where = self.frame, self.WHERE
        driving = [ego.id for ego in frame.egos if not _over(ego)]
        if frame.terminated and driving:
            self.rule(
                f"{where}.terminated",
                True,
                f"true only once no ego is left driving; {driving} still drive (§3.1)",
            )
        elif not frame.terminated and frame.egos and not driving:
            self.rule(f"{where}.terminated", False, "true: no ego is left driving (§3.1)")
        elif frame.terminated:
            reasons = {ego.reason for ego in frame.egos if ego.reason}
            if frame.reason not in reasons or not _reason_ok(
                frame.reason, TERMINAL_REASONS, self.checker.newer
            ):
                self.rule(
                    f"{where}.reason",
                    frame.reason,
                    f"the reason of the last ego's end: one of {sorted(reasons)} (§3.1)",
                )
        elif frame.reason:
            self.rule(f"{where}.reason", frame.reason, '"" while an ego drives (§3.1)')

    def egos(self) -> None:
        """Each ego's observation by the rules of an observation, against its last one."""
        frame, request, checker = self.frame, self.request, self.checker
        commands = {c.id: c for c in request.commands} if isinstance(request, MultiStep) else {}
        for i, ego in enumerate(frame.egos):
            asked: Request | None = request if isinstance(request, Reset) else None
            command = commands.get(ego.id)
            if command is not None:
                asked = Step(frame.seq, command.acceleration, command.lane_change)
            last = checker.last_egos.get(ego.id) if self.last is not None else None
            rules = _ObservationRules(
                checker, self.rule, ego_observation(frame, ego), asked, last,
                f"{self.WHERE}.egos[{i}]", "ends its ego's drive (§3.1)",
            )  # fmt: skip
            rules.body()
            if isinstance(request, MultiStep) and command is None:  # one that joins (1.5)
                rules.first("when it joins (§3.1)")


def _over(ego: EgoObservation) -> bool:
    return ego.terminated or ego.truncated


def _reason_ok(reason: str, allowed: frozenset[str], newer: bool) -> bool:
    """A reason of `allowed`, or one a newer minor version may have added."""
    return reason in allowed or (newer and bool(reason) and reason not in _ALL_REASONS)


def _traffic_problems(traffic: Traffic | None, where: str, rule: _Rules) -> None:
    """Every column of `traffic` as long as its ids (§4.8)."""
    if traffic is None:
        return
    count = len(traffic.id)
    for name in _TRAFFIC_COLUMNS:
        column = getattr(traffic, name)
        if len(column) != count:
            rule(
                f"{where}.traffic.{name}",
                len(column),
                f"as many items as traffic.id ({count}) (§4.8)",
            )


_TRAFFIC_COLUMNS = tuple(f.name for f in fields(Traffic))

_ALL_REASONS = TERMINAL_REASONS | TRUNCATION_REASONS


def _close(value: float, expected: float) -> bool:
    return abs(value - expected) <= TOLERANCE * max(1.0, abs(expected))


def _one_of(values: frozenset[str]) -> str:
    return ", ".join(sorted(values))


def _show(value: object) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value) if isinstance(value, str) else str(value)
