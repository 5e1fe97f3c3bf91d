"""A recording served back: ``sim-server --backend replay --recording DIR`` (docs/recording.md).

The backend answers as the recorded simulator did: it announces the recorded welcome, and a
reset and steps that match a recorded episode get that episode's replies, errors included, so
learner and evaluation code can be tested without the simulator. A request that departs from
every recorded episode is refused with an error naming what differs, and the server goes on
serving: the next matching reset replays again.

Which code answers which departure (docs/recording.md, "Replay"): a scenario never recorded
``unknown_scenario``; a seed not recorded for it ``invalid_number``; options that differ
``invalid_option``; a step whose acceleration or lane change is not the recorded one (float
equality) ``invalid_number``; a step beyond the end of a recorded episode ``out_of_order``.
"""

from __future__ import annotations

from pathlib import Path

from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import Error, Observation, OptionValue, ScenarioInfo, Step, Welcome
from protocol.recording import RecordedEpisode, load
from sim_server.backends.base import Backend
from sim_server.backends.options import merge_options
from sim_server.errors import BackendError

_SHOWN_SEEDS = 10
"""Seeds a refusal lists at most (an error message must stay short)."""


class ReplayBackend(Backend):
    """The episodes of a recording folder, served as the recorded simulator served them."""

    name = "replay"

    def __init__(self, folder: Path) -> None:
        """Read the whole recording; `protocol.recording.RecordingError` if it cannot be read."""
        self.recording = load(folder)
        self._welcome = self.recording.welcome
        self.sensor_range = self._welcome.sensor_range
        self.action_schema = self._welcome.action
        scenarios = {s.name: s for s in self._welcome.scenarios}
        self._episodes = [
            (episode, options)
            for episode in self.recording.episodes
            if (options := _merged(scenarios.get(episode.reset.scenario), episode)) is not None
        ]
        self._candidates: list[RecordedEpisode] = []
        """The recorded episodes the running one has matched so far."""

    @property
    def version(self) -> str:
        return f"{self._welcome.backend} {self._welcome.backend_version} (recorded)"

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return self._welcome.scenarios

    def welcome(self, ours: Welcome) -> Welcome:
        """The recorded welcome: the client sees the recorded server's schemas and scenarios."""
        return self._welcome

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        self._candidates = []
        matching = self._matching_resets(scenario, seed, options)
        first = matching[0].reply
        if isinstance(first, Error):
            raise _recorded(first)
        self._candidates = [episode for episode in matching if episode.reply == first]
        return first

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        candidates = [episode for episode in self._candidates if len(episode.steps) >= seq]
        self._candidates = []
        if not candidates:
            raise BackendError(
                ErrorCode.OUT_OF_ORDER,
                f"step {seq} is beyond the recording: the recorded episode stops before it",
            )
        matching = [
            episode
            for episode in candidates
            if _same(episode.steps[seq - 1].step, acceleration, lane_change)
        ]
        if not matching:
            recorded = candidates[0].steps[seq - 1].step
            raise BackendError(
                ErrorCode.INVALID_NUMBER,
                f"step {seq} departs from the recording: acceleration {acceleration!r} m/s^2 and "
                f"lane change {lane_change}, recorded {recorded.acceleration!r} m/s^2 and "
                f"{recorded.lane_change}",
            )
        reply = matching[0].steps[seq - 1].reply
        self._candidates = [e for e in matching if e.steps[seq - 1].reply == reply]
        if isinstance(reply, Error):
            raise _recorded(reply)
        return reply

    def close(self) -> None:
        self._candidates = []

    def _matching_resets(
        self, scenario: str, seed: int, options: dict[str, OptionValue]
    ) -> list[RecordedEpisode]:
        """The recorded episodes this reset replays; refused naming what departs from them."""
        of_scenario = [(e, o) for e, o in self._episodes if e.reset.scenario == scenario]
        if not of_scenario:
            recorded = sorted({e.reset.scenario for e, _ in self._episodes})
            raise BackendError(
                ErrorCode.UNKNOWN_SCENARIO,
                f"scenario {scenario!r} departs from the recording: recorded scenarios: "
                f"{', '.join(recorded) or 'none'}",
            )
        of_seed = [(e, o) for e, o in of_scenario if e.reset.seed == seed]
        if not of_seed:
            raise BackendError(
                ErrorCode.INVALID_NUMBER,
                f"seed {seed} departs from the recording: recorded seeds of {scenario}: "
                + _seeds({e.reset.seed for e, _ in of_scenario}),
            )
        matching = [e for e, o in of_seed if o == options]
        if not matching:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"the options of {scenario} seed {seed} depart from the recording: "
                + _difference(options, of_seed[0][1]),
            )
        return matching


def _merged(info: ScenarioInfo | None, episode: RecordedEpisode) -> dict[str, OptionValue] | None:
    """The options the recorded simulator received for `episode` (None: the session refused
    them, so no reset reaches the backend with them)."""
    if info is None:
        return None
    try:
        return merge_options(info, episode.reset.options)
    except ProtocolError:
        return None


def _same(recorded: Step, acceleration: float, lane_change: int) -> bool:
    """The step asks for what was recorded: float equality, no tolerance."""
    return recorded.acceleration == acceleration and recorded.lane_change == lane_change


def _recorded(reply: Error) -> BackendError:
    """The recorded error reply, raised again (an unknown code as ``simulator_error``)."""
    try:
        code = ErrorCode(reply.code)
    except ValueError:
        code = ErrorCode.SIMULATOR_ERROR
    return BackendError(code, reply.message)


def _seeds(seeds: set[int | None]) -> str:
    """A short list of recorded seeds (None: a reset without a seed)."""
    shown = sorted(seeds, key=lambda s: -1 if s is None else s)
    text = ", ".join("none" if s is None else str(s) for s in shown[:_SHOWN_SEEDS])
    return text + (f", ... ({len(shown)} in all)" if len(shown) > _SHOWN_SEEDS else "")


def _difference(given: dict[str, OptionValue], recorded: dict[str, OptionValue]) -> str:
    """The first option whose value differs from the recorded one, as ``name = given (recorded
    value)``."""
    for name in sorted(given.keys() | recorded.keys()):
        if given.get(name) != recorded.get(name):
            return f"option {name} = {given.get(name)!r}, recorded {recorded.get(name)!r}"
    return "their types differ"
