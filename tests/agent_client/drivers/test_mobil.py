"""IDM + MOBIL: the lane changes a route needs, MOBIL's discretionary ones, and its safety."""

from __future__ import annotations

import pytest

from agent_client.drivers.mobil import IDMMobilDriver
from agent_client.drivers.spec import load_driver
from protocol.messages import ROAD_RANGE, Ego, Neighbour, Neighbours, Observation, Road
from tests.protocol.test_codec import make_observation

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)
SPEED = 25.0


def scene(
    lane: int = 0,
    lanes: int = 3,
    road: Road | None = None,
    seq: int = 10,
    time: float = 60.0,
    speed: float = SPEED,
    **near: Neighbour,
) -> Observation:
    """The ego at `speed` in `lane` of `lanes` (100 km/h road) among the neighbours named."""
    slots = ("left_leader", "left_follower", "leader", "follower", "right_leader", "right_follower")
    return make_observation(
        seq=seq,
        time=time,
        ego=Ego(speed, 0.0, lane, lanes, 300.0, 27.78),
        neighbours=Neighbours(*(near.get(slot, ABSENT) for slot in slots)),
        road=road,
        ceiling=None,
    )


def merging(lane_end: float) -> Road:
    return Road(lane_end, 1, ROAD_RANGE, 0.0)


def test_it_merges_as_soon_as_the_gap_is_safe() -> None:
    _, lane = IDMMobilDriver().act(scene(road=merging(180.0)))
    assert lane == 1


def test_a_strategic_change_waits_for_a_safe_gap_and_adapts_its_speed() -> None:
    driver = IDMMobilDriver()
    alongside = Neighbour(True, 3.0, 3.2, SPEED, "beside")
    behind_it, lane = driver.act(scene(road=merging(400.0), left_leader=alongside))
    assert lane == 0  # not yet urgent: no request into an unsafe gap
    alone, _ = IDMMobilDriver().act(scene(road=merging(400.0)))
    assert behind_it < 0.0 < alone  # it falls back behind the vehicle beside it


def test_near_the_lane_end_it_asks_at_every_decision_and_brakes_for_the_end() -> None:
    driver = IDMMobilDriver()
    close_behind = Neighbour(True, 2.0, 3.2, 20.0, "lag")
    acceleration, lane = driver.act(
        scene(road=merging(25.0), speed=15.0, left_follower=close_behind)
    )
    assert lane == 1  # the simulator's own gap check refuses it if the gap is unsafe
    assert acceleration <= -3.0


def test_no_change_leads_away_from_the_route() -> None:
    """Slow leaders ahead and to the left, the right lane free: MOBIL would go right, but the
    route leaves to the left (beyond the look-ahead: not strategic yet)."""
    slow, slow_left = Neighbour(True, 15.0, 0.0, 10.0, "slow"), Neighbour(True, 15.0, 3.2, 10.0)
    open_road = scene(lane=1, leader=slow, left_leader=slow_left)
    assert IDMMobilDriver().act(open_road)[1] == -1
    to_the_left = Road(900.0, 1, 900.0, 900.0)
    blocked = scene(lane=1, road=to_the_left, leader=slow, left_leader=slow_left)
    assert IDMMobilDriver().act(blocked)[1] != -1
    assert IDMMobilDriver().act(scene(lane=0, leader=slow))[1] == 1  # open road: passes


def test_it_does_not_change_into_a_lane_that_ends_soon() -> None:
    slow_leader = Neighbour(True, 15.0, 0.0, 10.0, "slow")
    ending_left = Road(ROAD_RANGE, 0, 120.0, 0.0)
    _, lane = IDMMobilDriver().act(scene(lane=0, road=ending_left, leader=slow_leader))
    assert lane == 0


def test_mobil_passes_a_slow_leader_once_a_second_if_safe() -> None:
    driver = IDMMobilDriver()
    slow = Neighbour(True, 15.0, 0.0, 10.0, "slow")
    assert driver.act(scene(lane=0, leader=slow, time=60.0))[1] == 1
    assert driver.act(scene(lane=0, leader=slow, time=60.5))[1] == 0  # within the second
    assert driver.act(scene(lane=0, leader=slow, time=61.0))[1] == 1
    fast_behind = Neighbour(True, 5.0, 3.2, 30.0, "fast")
    assert IDMMobilDriver().act(scene(lane=0, leader=slow, left_follower=fast_behind))[1] == 0


def test_keeping_right_needs_no_gain_but_leaving_it_does() -> None:
    """The bias (0.2 m/s²) against leaving the right: a leader whose gain is ~0.3 m/s² is
    passed on the right lane's side from the middle, never by moving left."""
    assert IDMMobilDriver().act(scene(lane=1))[1] == 0  # an empty road: nothing to gain
    leader = Neighbour(True, 100.0, 0.0, 24.0, "a little slower")
    unlimited = 100.0  # s: a decision interval that lifts the jerk limit, to see IDM's own
    free = IDMMobilDriver().acceleration(scene(lane=1), unlimited)
    gain = free - IDMMobilDriver().acceleration(scene(lane=1, leader=leader), unlimited)
    assert 0.2 < gain < 0.2 + 0.2  # above the threshold, below threshold + bias
    assert IDMMobilDriver().act(scene(lane=1, leader=leader))[1] == -1  # right: threshold only
    assert IDMMobilDriver().act(scene(lane=0, leader=leader))[1] == 0  # left: + bias


@pytest.mark.parametrize("spec", ["idm+mobil", "sumo"])
def test_the_specs_name_the_models(spec: str) -> None:
    driver = load_driver(spec)
    assert getattr(driver, "name", "") == spec
    if spec == "sumo":
        assert driver.reset_options == {"ego_driver": "sumo"}  # type: ignore[attr-defined]
