"""The interface between the server loop and a simulator.

The server owns the socket, the session and the protocol; a backend owns one simulation. To put
another simulator behind the bridge, implement `Backend` (or write a server in any language that
speaks docs/protocol.md).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

from protocol.errors import ErrorCode
from protocol.messages import ActionSchema, Observation, OptionValue, ScenarioInfo

DEFAULT_SENSOR_RANGE = 200.0
"""Metres within which neighbours are reported as present."""

LANE_CHANGE_TIMEOUT_S = 5.0
"""A commanded lane change not completed this long after it started is given up
(`Events.lane_change_aborted`). SUMO drops a lane-change request it could not begin within the
request's 2 s (the gap closed meanwhile); without a timeout the ego would wait for it forever."""

DEFAULT_ACTION_SCHEMA = ActionSchema(acceleration_min=-6.0, acceleration_max=3.0)
"""Comfortable-to-hard braking down to -6 m/s^2, acceleration up to +3 m/s^2."""


@dataclass(frozen=True)
class LaneChange:
    """A commanded lane change under way, from the step that started it until it completes."""

    target: int
    """The lane the ego moves to, in the simulator's own numbering."""
    direction: int
    """As commanded and reported in `Ego.changing_lane`: 1 left, -1 right."""
    started: float
    """Simulation time of the step that started it (s)."""

    def expired(self, now: float) -> bool:
        """Not completed within `LANE_CHANGE_TIMEOUT_S`: give it up."""
        return now - self.started >= LANE_CHANGE_TIMEOUT_S - 1e-9


class BackendError(Exception):
    """A failure the server reports as an `Error` reply with `code`."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class Backend(ABC):
    """One simulation with one controlled ego vehicle."""

    name: str
    """Short backend name announced in `Welcome.backend`, e.g. "sumo"."""
    sensor_range: float = DEFAULT_SENSOR_RANGE
    action_schema: ActionSchema = DEFAULT_ACTION_SCHEMA

    @property
    @abstractmethod
    def version(self) -> str:
        """Version of the simulator behind the backend."""

    @abstractmethod
    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        """Scenarios offered, each with its options and their defaults."""

    @abstractmethod
    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        """Start an episode; `options` are complete and type-checked. Returns seq 0."""

    @abstractmethod
    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        """Apply one decision (acceleration not yet clipped) and return the state after it."""

    @abstractmethod
    def close(self) -> None:
        """Release the simulator."""
