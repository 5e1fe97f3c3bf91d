"""The red-light watch on its own, against SUMO's getNextTLS answers as a stub gives them: a
light that appears ahead of the one watched is no light passed."""

from __future__ import annotations

from dataclasses import dataclass, field

from sim_server.backends.sumo.signals import RedLightWatch


@dataclass
class Vehicle:
    """What the watch asks of ``api.vehicle``: the next lights (id, link, metres, state)."""

    ahead: list[tuple[str, int, float, str]] = field(default_factory=list)
    lane: str = "road_0"

    def getNextTLS(self, ego_id: str) -> list[tuple[str, int, float, str]]:
        return self.ahead

    def getLaneID(self, ego_id: str) -> str:
        return self.lane

    def getSpeed(self, ego_id: str) -> float:
        return 10.0


class Simulation:
    def getDeltaT(self) -> float:
        return 0.1


@dataclass
class Api:
    vehicle: Vehicle = field(default_factory=Vehicle)
    simulation: Simulation = field(default_factory=Simulation)


def test_a_light_that_appears_ahead_of_the_watched_one_is_not_a_red_light_passed() -> None:
    api, watch = Api(), RedLightWatch()
    api.vehicle.ahead = [("far", 0, 200.0, "r")]
    assert not watch.passed_red(api, "ego")
    # Leaving a junction, SUMO reports a light 3 m on, before the far one (still red).
    api.vehicle.ahead = [("near", 1, 3.0, "G"), ("far", 0, 199.0, "r")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("far", 0, 190.0, "r")]  # the near one passed on green
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("far", 0, 1.0, "r")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = []  # the far one passed while red
    assert watch.passed_red(api, "ego") and watch.passed == "far"


def test_the_same_light_again_farther_on_means_the_first_was_passed() -> None:
    api, watch = Api(), RedLightWatch()
    api.vehicle.ahead = [("joined", 0, 2.0, "r"), ("joined", 3, 120.0, "G")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("joined", 3, 119.0, "G")]  # a joined light's next stop line
    assert watch.passed_red(api, "ego")


def test_a_far_light_whose_distance_grows_is_not_passed() -> None:
    # Entering a junction (or changing lanes), SUMO's distance to a light far on may grow.
    api, watch = Api(), RedLightWatch()
    api.vehicle.ahead = [("far", 5, 948.3, "r")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("far", 5, 949.1, "r")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("far", 5, 2.0, "r")]
    assert not watch.passed_red(api, "ego")
    api.vehicle.ahead = [("next", 0, 300.0, "G")]  # crossed at 10 m/s within the step: red
    assert watch.passed_red(api, "ego")
