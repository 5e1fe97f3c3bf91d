"""Scenario options as typed values, parsed and range-checked once per reset.

The session merges a client's options into the scenario's announced defaults and checks their
names and types (`Backend.reset` receives that dict). A backend turns the dict into these frozen
dataclasses at once and reads typed fields from then on. Every refusal is a `BackendError` with
``invalid_option``; the announced defaults are the dataclasses' own (`as_options`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import Field, dataclass, fields
from typing import Any, ClassVar, Self, TypeVar

from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import OptionValue, ScenarioInfo
from sim_server.errors import BackendError


def invalid_option(message: str) -> BackendError:
    return BackendError(ErrorCode.INVALID_OPTION, message)


@dataclass(frozen=True, slots=True)
class Bounds:
    """The accepted values of a numeric option: ``low <= value <= high`` (or ``low < value``).

    An absurd value must be refused, not freeze the simulator: every number has an upper bound.
    """

    low: float
    high: float
    low_excluded: bool = False
    unit: str = ""
    """Said after the upper bound in a refusal, e.g. ``veh/h/lane``."""
    text: str = ""
    """The whole range as a refusal says it (``within [0, 1]``), instead of the failed bound."""

    def check(self, name: str, value: float) -> None:
        """Raise ``invalid_option`` naming `name` and the bound if `value` is out of range."""
        too_low = not (value > self.low if self.low_excluded else value >= self.low)
        if self.text and (too_low or not value <= self.high):
            raise invalid_option(f"option {name} must be {self.text}")
        if not value <= self.high:
            raise invalid_option(f"option {name} must be <= {self.high:g}{self.unit}")
        if too_low:
            relation = ">" if self.low_excluded else ">="
            raise invalid_option(f"option {name} must be {relation} {self.low:g}")


class ParsedOptions:
    """Base of the option dataclasses: parse from the merged dict, announce the defaults.

    Each field's default is the announced default and fixes its wire type; `BOUNDS` holds the
    range of each numeric field. A key missing from the dict takes the field's default.
    """

    __slots__ = ()
    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]
    BOUNDS: ClassVar[Mapping[str, Bounds]] = {}

    @classmethod
    def parse(cls, options: Mapping[str, OptionValue]) -> Self:
        """The fields from `options`, each of its default's type and within its bounds."""
        parsed = _parse_fields(cls, options)
        parsed.check()
        return parsed

    def check(self) -> None:
        """Checks across fields, after each field was checked alone (none by default)."""

    def as_options(self) -> dict[str, OptionValue]:
        """The fields as scenario options, in declaration order (the order announced)."""
        return {spec.name: getattr(self, spec.name) for spec in fields(self)}


def _parse_fields(cls: type[_Parsed], options: Mapping[str, OptionValue]) -> _Parsed:
    defaults = cls()
    values: dict[str, Any] = {}
    for spec in fields(cls):
        default = getattr(defaults, spec.name)
        value = _typed(spec.name, options.get(spec.name, default), default)
        bounds = cls.BOUNDS.get(spec.name)
        if bounds is not None and isinstance(value, int | float):
            bounds.check(spec.name, value)
        values[spec.name] = value
    return cls(**values)


_Parsed = TypeVar("_Parsed", bound=ParsedOptions)


def _typed(name: str, value: OptionValue, default: Any) -> OptionValue:
    """`value` as the type of `default` (an int is accepted for a float), or refused."""
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if type(value) is not type(default):
        raise invalid_option(
            f"option {name} must be {type(default).__name__}, got {type(value).__name__}"
        )
    return value


MAX_EGOS = 1024
"""The most egos one episode can have: the protocol's longest array."""


@dataclass(frozen=True, slots=True)
class EpisodeOptions(ParsedOptions):
    """The options every scenario of every backend shares (docs/protocol.md §6)."""

    decision_interval: float = 0.1
    """Seconds per step: the action is repeated over this many seconds of simulation."""
    max_episode_time: float = 300.0
    """Seconds after the ego's entry; then the episode is truncated (``time_limit``)."""
    warmup: float = 30.0
    """Seconds of simulation before the client drives the ego."""
    insertion_timeout: float = 60.0
    """Seconds the ego may wait to enter; then ``insertion_failed``."""
    stop_speed: float = 1.0
    """The unreasonable stop (``stopped``): the ego slower than this (m/s), with no leader or
    one more than `stop_gap` ahead and faster, for `stop_patience`; not within `stop_gap` of a
    stop line (protocol 1.7), and `lane_end_patience` for a stop that began at one."""
    stop_gap: float = 15.0
    """Metres; see `stop_speed`."""
    stop_patience: float = 2.0
    """Seconds; see `stop_speed`."""
    lane_end_patience: float = 10.0
    """Seconds the ego may stand (slower than `stop_speed`) within `stop_gap` of the end of a
    lane that does not continue its route, waiting for a gap; then ``lane_end`` (since protocol
    1.6)."""
    jam_patience: float = 120.0
    """Seconds the ego may stand (slower than `stop_speed`), whatever holds it (a queue, a red
    light, a gridlock); then ``jammed`` (since protocol 1.8)."""
    end_on_red_light: bool = False
    """End the episode (``red_light``) when the ego passes a red light (since protocol 1.8);
    false: the event is reported and the drive goes on."""
    report_ceiling: bool = True
    """Report the leader-at-entry's trip on the last observation."""
    ego_driver: str = "agent"
    """"agent": the client drives; otherwise the simulator's own driver model does."""
    egos: int = 1
    """Controlled vehicles (since protocol 1.4): a reset that names it gets `MultiObservation`
    replies and is stepped with `MultiStep`; how a backend places them is its own."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "decision_interval": Bounds(0.0, 60.0, low_excluded=True),
        "max_episode_time": Bounds(0.0, 86_400.0, low_excluded=True),
        "warmup": Bounds(0.0, 3600.0),
        "insertion_timeout": Bounds(0.0, 3600.0, low_excluded=True),
        "stop_speed": Bounds(0.0, 100.0),
        "stop_gap": Bounds(0.0, 10_000.0),
        "stop_patience": Bounds(0.0, 3600.0),
        "lane_end_patience": Bounds(0.0, 3600.0),
        "jam_patience": Bounds(0.0, 86_400.0, low_excluded=True),
        "egos": Bounds(1, MAX_EGOS),
    }

    @classmethod
    def parse(
        cls, options: Mapping[str, OptionValue], simulator_drivers: tuple[str, ...] = ("sumo",)
    ) -> Self:
        """As `ParsedOptions.parse`; `ego_driver` must be "agent" or one of `simulator_drivers`
        (the first is its name, the others are aliases)."""
        parsed = _parse_fields(cls, options)
        parsed.check()
        if parsed.ego_driver != "agent" and parsed.ego_driver not in simulator_drivers:
            name, *aliases = simulator_drivers
            also = f" ({', '.join(aliases)} is accepted as an alias)" if aliases else ""
            raise invalid_option(f"option ego_driver must be agent or {name}{also}")
        return parsed

    @property
    def simulator_drives(self) -> bool:
        """The simulator's driver model drives the ego; the client's actions are ignored."""
        return self.ego_driver != "agent"

    def steps_per_decision(self, step_length: float) -> int:
        """Simulation steps per decision; refused unless the interval is a multiple of them."""
        interval = self.decision_interval
        steps = round(interval / step_length)
        if steps < 1 or abs(steps * step_length - interval) > 1e-6:
            raise invalid_option(
                f"decision_interval {interval} s is not a multiple of the step length "
                f"{step_length} s"
            )
        return steps


@dataclass(frozen=True, slots=True)
class TrafficOptions(ParsedOptions):
    """The human traffic of the built-in SUMO roads (they change the route file)."""

    flow: float = 1500.0
    """Vehicles per hour and lane, Poisson arrivals."""
    speed_factor_mean: float = 0.85
    """Mean desired speed of the humans, as a fraction of the speed limit."""
    speed_factor_dev: float = 0.15
    """Its standard deviation (a normal distribution truncated to [0.5, 1.5])."""
    sigma: float = 0.5
    """Krauss driver imperfection of the humans."""
    human_model: str = "krauss"
    """The humans' car-following model: krauss, idm, eidm or w99 (Wiedemann 99, VISSIM's)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "flow": Bounds(0.0, 3600.0, unit=" veh/h/lane"),
        "speed_factor_mean": Bounds(0.0, 3.0, low_excluded=True),
        "speed_factor_dev": Bounds(0.0, 3.0),
        "sigma": Bounds(0.0, 1.0, text="within [0, 1]"),
    }

    def check(self) -> None:
        if self.human_model not in HUMAN_MODEL_NAMES:
            raise invalid_option(
                f"option human_model must be one of {', '.join(HUMAN_MODEL_NAMES)}, "
                f"got {self.human_model[:64]!r}"
            )


HUMAN_MODEL_NAMES = ("krauss", "idm", "eidm", "w99")
"""The humans' car-following models a backend may offer (`TrafficOptions.human_model`)."""


@dataclass(frozen=True, slots=True)
class ShareOptions(ParsedOptions):
    """Egos as a share of the traffic (since protocol 1.5), announced by the backends that
    offer it: a reset that names ``ego_share`` starts a multi-ego episode (§3.1)."""

    ego_share: float = 0.0
    """The share of the vehicles that are egos: of those on the road at the hand-over, and of
    each that enters afterwards; 0 (the default) when the reset does not name it."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "ego_share": Bounds(0.0, 1.0, text="within (0, 1]"),
    }


COMMON_OPTIONS = EpisodeOptions().as_options()
"""The announced defaults of the options every scenario accepts (copy before changing)."""
TRAFFIC_OPTIONS = TrafficOptions().as_options()
"""The announced defaults of the built-in roads' traffic options (copy before changing)."""
SHARE_OPTIONS = ShareOptions().as_options()
"""The announced default of ``ego_share``, for the backends that offer it."""


def merge_options(info: ScenarioInfo, given: dict[str, OptionValue]) -> dict[str, OptionValue]:
    """Scenario defaults overridden by the client's options, with names and types checked.

    The session merges every reset's options so (a backend receives the result); a fault is a
    `ProtocolError` with ``invalid_option``."""
    merged = dict(info.options)
    for name, value in given.items():
        if name not in merged:
            raise ProtocolError(
                ErrorCode.INVALID_OPTION,
                f"scenario {info.name} has no option {name[:64]!r}; options: {', '.join(merged)}",
            )
        default = merged[name]
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if default is not None and type(value) is not type(default):
            raise ProtocolError(
                ErrorCode.INVALID_OPTION,
                f"option {name} must be {type(default).__name__}, got {type(value).__name__}",
            )
        merged[name] = value
    return merged
