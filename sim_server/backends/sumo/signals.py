"""Traffic lights on the ego's route: the next one's state (protocol 1.8), and red lights passed.

`vehicle.getNextTLS` lists the lights ahead on a vehicle's route, each as (light id, link index,
metres to its stop line, the link's state character). SUMO's characters: ``r`` red, ``u`` red
and yellow (about to turn green: still closed), ``y``/``Y`` yellow, ``g``/``G`` green without /
with priority, ``s`` a green right-turn arrow (stop, then go), ``o``/``O`` off (blinking / no
signal: the junction's right of way applies). The time to the next change walks the light's
programme from `trafficlight.getNextSwitch` (an actuated light's phases may still be stretched:
the figure is the programme as it stands).

The ego drives with SUMO's checks off (speed mode 32), so SUMO lets it cross a red stop line;
`RedLightWatch` sees it happen: the light that was next on the route is no longer ahead, and the
ego's link there was red when it was last seen before the line.

Source: SUMO docs, TraCI "Vehicle Value Retrieval" (next TLS, 0x70), "Traffic Lights Value
Retrieval" (0x2d next switch, complete program definition); "Traffic Lights" (signal state
definitions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from protocol.messages import ROAD_RANGE, SIGNAL_HORIZON, SignalState
from sim_server.backends.sumo.road import YELLOW_DECELERATION

STATE_OF: dict[str, SignalState] = {
    "r": SignalState.RED,
    "u": SignalState.RED,
    "y": SignalState.YELLOW,
    "Y": SignalState.YELLOW,
    "g": SignalState.GREEN,
    "G": SignalState.GREEN,
    "s": SignalState.GREEN,
    "o": SignalState.OFF,
    "O": SignalState.OFF,
}
"""SUMO's link state characters -> the protocol's signal states (an unknown one reads as off)."""
RED_CHARACTERS = frozenset("ru")
"""The states in which crossing the stop line is passing a red light."""
PASSED_SLACK = 0.5
"""m: a next light farther than the last one seen is another light (the one seen before is
behind the ego): approaching a light, its distance only shrinks (a lane change beside keeps
it)."""

REACH_SLACK = 2.0
"""m: a light is passed in a simulation step only if it was at most this much farther than the
ego drives in that step (at its speed, half as much again) when seen last: entering a junction
or changing lanes, SUMO's distance to a light hundreds of metres on may grow by a metre, which
passes nothing."""

_ID, _INDEX, _DISTANCE, _STATE = 0, 1, 2, 3
"""Positions in a `vehicle.getNextTLS` entry."""


@dataclass(frozen=True, slots=True)
class Signal:
    """The next traffic light on the ego's route, as `protocol.messages.Road` reports it."""

    distance: float
    state: SignalState
    switch: float


NO_SIGNAL = Signal(ROAD_RANGE, SignalState.NONE, 0.0)


class Programmes:
    """The phases of every light's running programme, asked of SUMO once per light and
    programme (a network's lights keep theirs for the run; a new network needs a new one)."""

    def __init__(self, api: Any) -> None:
        self._api = api
        self._phases: dict[str, tuple[str, list[tuple[float, str]]]] = {}
        self._indices: dict[tuple[str, str, str], int] = {}

    def phases(self, light: str) -> list[tuple[float, str]]:
        """(duration, state string) of each phase of `light`'s running programme."""
        lights = self._api.trafficlight
        program = lights.getProgram(light)
        known = self._phases.get(light)
        if known is None or known[0] != program:
            logic = next(
                (p for p in lights.getAllProgramLogics(light) if p.programID == program), None
            )
            phases = [(p.duration, p.state) for p in logic.phases] if logic is not None else []
            known = self._phases[light] = (program, phases)
        return known[1]

    def link_index(self, light: str, from_lane: str, to_lane: str) -> int:
        """The index in `light`'s state of the connection `from_lane` -> `to_lane`; -1 where
        the light does not control it."""
        key = (light, from_lane, to_lane)
        index = self._indices.get(key)
        if index is None:
            links = self._api.trafficlight.getControlledLinks(light)
            index = self._indices[key] = next(
                (
                    k
                    for k, connections in enumerate(links)
                    if any(c[0] == from_lane and c[1] == to_lane for c in connections)
                ),
                -1,
            )
        return index

    def switch_in(self, light: str, index: int, now: float) -> float:
        """Seconds until the state of link `index` of `light` changes class (red, yellow,
        green, off), by its programme from the current phase on; `SIGNAL_HORIZON` at most."""
        lights = self._api.trafficlight
        phases = self.phases(light)
        remaining = max(lights.getNextSwitch(light) - now, 0.0)
        if not phases:
            return min(remaining, SIGNAL_HORIZON)
        current = lights.getPhase(light) % len(phases)
        now_class = _state_class(phases[current][1], index)
        elapsed = remaining
        for step in range(1, len(phases) + 1):
            if elapsed >= SIGNAL_HORIZON:
                break
            duration, state = phases[(current + step) % len(phases)]
            if _state_class(state, index) != now_class:
                return elapsed
            elapsed += duration
        return SIGNAL_HORIZON


def _state_class(state: str, index: int) -> SignalState:
    character = state[index] if 0 <= index < len(state) else "o"
    return STATE_OF.get(character, SignalState.OFF)


def signal_line(signal: Signal, speed: float, limit_before: float = math.inf) -> float:
    """Metres to the stop line of the next traffic light where it closes the ego's way now:
    red; yellow where stopping needs no more than `YELLOW_DECELERATION` or the ego at its speed
    (no faster than `limit_before`, the lowest speed limit on its way to the line, which SUMO
    holds it to) would not reach the line before it turns red. `ROAD_RANGE` otherwise (also
    where the light is beyond other junctions: `Road.stop_line` is then the nearer of the
    two)."""
    if signal.state == SignalState.RED:
        return signal.distance
    if signal.state == SignalState.YELLOW:
        room, reach = signal.distance, min(speed, limit_before)
        if speed * speed <= 2.0 * YELLOW_DECELERATION * room or room > reach * signal.switch:
            return room
    return ROAD_RANGE


def next_signal(
    api: Any, ego_id: str, programmes: Programmes, now: float, inside: str = ""
) -> Signal:
    """The next traffic light on `ego_id`'s route within `ROAD_RANGE`, or `NO_SIGNAL`; not the
    light `inside` (the one whose junction the ego is crossing: its waiting point inside,
    where a turn across oncoming traffic waits, is under the same light, whose colour no
    longer concerns a vehicle already in the junction)."""
    for light, index, distance, character in api.vehicle.getNextTLS(ego_id):
        if light == inside:
            continue
        if distance >= ROAD_RANGE:
            break
        state = STATE_OF.get(character, SignalState.OFF)
        switch = programmes.switch_in(light, index, now)
        return Signal(max(distance, 0.0), state, switch)
    return NO_SIGNAL


class RedLightWatch:
    """Whether an ego crossed a red stop line since the last look (every simulation step where
    the network has lights)."""

    __slots__ = ("_ahead", "passed")

    def __init__(self) -> None:
        self._ahead: tuple[str, float, str] | None = None
        """The light next on the route at the last look: (id, metres to it, link state)."""
        self.passed = ""
        """The light whose stop line the ego crossed last."""

    def inside(self, api: Any, ego_id: str) -> str:
        """The light of the junction the ego is crossing ("" when it is on a road): the one
        it passed last, while it is on a junction's internal lane."""
        if self.passed and api.vehicle.getLaneID(ego_id).startswith(":"):
            return self.passed
        return ""

    def passed_red(self, api: Any, ego_id: str) -> bool:
        """Look again; True if the light seen last is behind the ego now and its link was red
        or red-yellow when last seen before it (a simulation step earlier). Inside a junction
        the waiting point under the same light is no stop line: the ego clears the junction."""
        inside = self.inside(api, ego_id)
        ahead = [e for e in api.vehicle.getNextTLS(ego_id) if e[_ID] != inside]
        first = ahead[0] if ahead else None
        seen = self._ahead
        self._ahead = None if first is None else (first[_ID], first[_DISTANCE], first[_STATE])
        if seen is None:
            return False
        light, distance, character = seen
        # Passed when that light, within a step's reach, is no longer ahead where it was: not
        # when another one came first (a light close behind a junction appears only once the
        # ego leaves it), nor when the distance to a far one grew (a lane change, a junction).
        reach = 1.5 * api.vehicle.getSpeed(ego_id) * api.simulation.getDeltaT() + REACH_SLACK
        passed = distance <= reach and not any(
            e[_ID] == light and e[_DISTANCE] <= distance + PASSED_SLACK for e in ahead
        )
        if passed:
            self.passed = light
        return passed and character in RED_CHARACTERS
