"""The interface between the server loop and a simulator.

The server owns the socket, the session and the protocol; a backend owns one simulation. To put
another simulator behind the bridge, implement `Backend` (or write a server in any language that
speaks docs/protocol.md). The rules every simulator applies alike are in `rules`, the typed
options in `options`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from protocol.messages import ActionSchema, Observation, OptionValue, ScenarioInfo, Welcome
from sim_server.errors import BackendError

__all__ = ["DEFAULT_ACTION_SCHEMA", "DEFAULT_SENSOR_RANGE", "Backend", "BackendError"]

DEFAULT_SENSOR_RANGE = 200.0
"""Metres within which neighbours are reported as present."""

DEFAULT_ACTION_SCHEMA = ActionSchema(acceleration_min=-6.0, acceleration_max=3.0)
"""Comfortable-to-hard braking down to -6 m/s^2, acceleration up to +3 m/s^2."""


class Backend(ABC):
    """One simulation with one controlled ego vehicle.

    Failures the client should hear of are raised as `BackendError` (the server answers with
    its code); anything else is reported as an internal ``simulator_error``.
    """

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

    def welcome(self, ours: Welcome) -> Welcome:
        """The welcome the server announces: `ours`, built from the attributes above (a backend
        that replays a recording announces the recorded one)."""
        return ours
