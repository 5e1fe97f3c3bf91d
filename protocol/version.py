"""Protocol version of the bridge wire format (semantic versioning).

Revision history:
    1.0  First release: hello/welcome handshake, reset/step/close, named observations
         with the six neighbours of the paper's Fig. 11, events and applied actions.
    1.1  `ego.changing_lane`: the direction of the lane change under way (0 from 1.0 servers);
         `events.lane_change_aborted`: a started lane change the simulator gave up.
    1.2  No new key; the contract made complete: `scenarios[].step_length` required; the
         server socket is a ROUTER with handover; one error code for every malformed request
         (non-string keys, bin and ext values are `decode_error`); the state machine's and the
         observation's corner cases and the well-known options' types specified.
    1.3  `observation.safety` (the simulator's surrogate safety measures of the episode, on its
         last observation) and `observation.traffic` (every other vehicle, each step), both
         only when a reset option asks for them (``ssm``, ``report_traffic``).
    1.4  Many egos in one simulation: a reset that names the option ``egos`` is answered with
         `multi_observation` (every ego's observation, per-ego ends) and stepped with
         `multi_step` (one command per running ego).
    1.5  Egos as a share of the traffic: a reset that names the option ``ego_share`` hands that
         share of the vehicles over, and the vehicles that enter later join the episode at the
         same share (a frame lists a joining ego after those that drove into the step).
    1.6  The road ahead: `observation.road` (and each ego's in a `multi_observation`): where
         the ego's lane ends along its route, which way and how many lanes lead on, and where
         the lanes beside it end; four fields of the flat vector, announced to 1.6 clients
         only; the end reason ``lane_end``.
    1.7  The stop line: `road.stop_line`, where the ego must stop now at the next junction on
         its route (a red light, a road that must give way to foes with priority); one field
         of the flat vector, announced to 1.7 clients only.
    1.8  Signals and the trip: `road.signal_distance`, `road.signal_state` and
         `road.signal_switch` (the next traffic light on the ego's route, three fields of the
         flat vector, announced to 1.8 clients only); `events.red_light` (a red light passed)
         and `events.collision_type` ("lane" or "junction"); `observation.route` (the ego's
         route and how much of it was driven, on the first and the last observation); the end
         reasons ``red_light`` (where a reset option asks for it) and ``jammed``.

The project's CHANGELOG.md ("Protocol versions") keeps this history beside the package releases.

Compatibility rule: peers with the same major version interoperate. A minor version only adds
optional fields or message types; receivers ignore map keys they do not know.
"""

from __future__ import annotations

PROTOCOL_VERSION: tuple[int, int] = (1, 8)

MANY_EGOS_VERSION: tuple[int, int] = (1, 4)
"""The first version with many egos in one simulation (`multi_step`, `multi_observation`)."""

EGO_SHARE_VERSION: tuple[int, int] = (1, 5)
"""The first version with egos as a share of the traffic (``ego_share``, egos joining)."""

ROAD_VERSION: tuple[int, int] = (1, 6)
"""The first version with the road ahead (`Road`, the ``lane_end`` end reason)."""

STOP_LINE_VERSION: tuple[int, int] = (1, 7)
"""The first version with the stop line (`Road.stop_line`)."""

SIGNAL_VERSION: tuple[int, int] = (1, 8)
"""The first version with signals (`Road.signal_distance` ...), `Events.red_light`, `Route`."""


def format_version(version: tuple[int, int]) -> str:
    """Render a version tuple as ``MAJOR.MINOR``."""
    return f"{version[0]}.{version[1]}"


def is_compatible(ours: tuple[int, int], theirs: tuple[int, int]) -> bool:
    """Two protocol versions interoperate when their major versions agree."""
    return ours[0] == theirs[0]
