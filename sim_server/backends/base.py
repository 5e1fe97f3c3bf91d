"""The interface between the server loop and a simulator.

The server owns the socket, the session and the protocol; a backend owns one simulation. To put
another simulator behind the bridge, implement `Backend` (or write a server in any language that
speaks docs/protocol.md). The rules every simulator applies alike are in `rules`, the typed
options in `options`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping

from protocol.errors import ErrorCode
from protocol.messages import (
    ActionSchema,
    EgoObservation,
    MultiObservation,
    Observation,
    OptionValue,
    ScenarioInfo,
    Welcome,
)
from sim_server.errors import BackendError

__all__ = [
    "DEFAULT_ACTION_SCHEMA",
    "DEFAULT_SENSOR_RANGE",
    "SINGLE_EGO_ID",
    "Backend",
    "BackendError",
    "Commands",
    "as_multi",
    "ego_part",
]

DEFAULT_SENSOR_RANGE = 200.0
"""Metres within which neighbours are reported as present."""

DEFAULT_ACTION_SCHEMA = ActionSchema(acceleration_min=-6.0, acceleration_max=3.0)
"""Comfortable-to-hard braking down to -6 m/s^2, acceleration up to +3 m/s^2."""


SINGLE_EGO_ID = "ego"
"""The ego's id when a one-ego backend answers a reset that names ``egos`` (= 1)."""

Commands = Mapping[str, tuple[float, int]]
"""A `MultiStep`'s commands by ego id: (acceleration not yet clipped, lane change)."""


def ego_part(ego_id: str, obs: Observation) -> EgoObservation:
    """One ego's part of a `MultiObservation`: its observation `obs` without the clock."""
    return EgoObservation(
        ego_id, obs.ego, obs.neighbours, obs.events, obs.action,
        obs.terminated, obs.truncated, obs.reason, obs.road,
    )  # fmt: skip


def as_multi(obs: Observation, ego_id: str = SINGLE_EGO_ID) -> MultiObservation:
    """A one-ego observation as the `MultiObservation` of a one-ego episode."""
    mine = ego_part(ego_id, obs)
    return MultiObservation(
        obs.seq, obs.time, (mine,), obs.terminated, obs.truncated, obs.reason, obs.traffic
    )


class Backend(ABC):
    """One simulation with one controlled ego vehicle (or, through `reset_many` and
    `step_many`, up to `max_egos` of them).

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

    max_egos: int = 1
    """How many egos `reset_many` accepts; a backend that drives several overrides both
    `reset_many` and `step_many`."""

    def reset_many(
        self, scenario: str, seed: int, options: dict[str, OptionValue], egos: int
    ) -> MultiObservation:
        """Start an episode with `egos` controlled vehicles (a reset naming ``egos``; seq 0).

        This default serves one ego through `reset`, under the id `SINGLE_EGO_ID`."""
        if egos > self.max_egos:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"option egos {egos}: this backend drives at most {self.max_egos} ego(s)",
            )
        return as_multi(self.reset(scenario, seed, options))

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        """Apply every running ego's command; the session has checked the ids are exactly the
        running egos'."""
        ((ego_id, (acceleration, lane_change)),) = commands.items()
        return as_multi(self.step(seq, acceleration, lane_change), ego_id)

    def welcome(self, ours: Welcome) -> Welcome:
        """The welcome the server announces: `ours`, built from the attributes above (a backend
        that replays a recording announces the recorded one)."""
        return ours
