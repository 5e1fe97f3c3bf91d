"""Every reply in bounded wall-clock time, whatever the network (real SUMO): a 50 km trip whose
end waits for the leader-at-entry, and a gridlock that never clears (teleporting off)."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.drivers.mobil import IDMMobilDriver
from protocol.messages import EndReason, OptionValue
from sim_server.backends.sumo.backend import CEILING_WALL_S, SumoBackend
from sim_server.backends.sumo.scenarios import CustomScenario, find_netconvert

pytestmark = pytest.mark.sumo

STEP_DEADLINE_S = 10.0
"""The client's deadline for a step's reply (`agent-client --timeout`'s default)."""


def netconvert(folder: Path, nodes: str, edges: str) -> None:
    (folder / "n.nod.xml").write_text(f"<nodes>{nodes}</nodes>\n")
    (folder / "n.edg.xml").write_text(f"<edges>{edges}</edges>\n")
    subprocess.run(
        [find_netconvert(), "--node-files", str(folder / "n.nod.xml"),
         "--edge-files", str(folder / "n.edg.xml"), "--output-file", str(folder / "n.net.xml"),
         "--no-turnarounds", "true"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip


def config(folder: Path, routes: str) -> Path:
    (folder / "n.rou.xml").write_text(f"<routes>{routes}</routes>\n")
    path = folder / "n.sumocfg"
    path.write_text(
        '<configuration><input><net-file value="n.net.xml"/><route-files value="n.rou.xml"/>'
        '</input><time><step-length value="0.1"/></time></configuration>\n'
    )
    return path


def write_long_road(folder: Path) -> Path:
    """One lane, 50 km, 1,200 veh/h driving all of it; the ego's route ``ego`` too."""
    netconvert(
        folder,
        '<node id="a" x="0" y="0"/><node id="b" x="50000" y="0"/>',
        '<edge id="road" from="a" to="b" numLanes="1" speed="25"/>',
    )
    return config(
        folder,
        '<route id="ego" edges="road"/>'
        '<flow id="f" route="ego" begin="0" end="86400" vehsPerHour="1200" departSpeed="max"/>',
    )


def write_gridlock(folder: Path) -> Path:
    """A one-lane block (four 80 m roads) that vehicles keep entering and circling: it fills,
    and with teleporting off its traffic stands for good. The ego's route ``ego`` enters it."""
    netconvert(
        folder,
        '<node id="a" x="0" y="0"/><node id="b" x="80" y="0"/><node id="c" x="80" y="80"/>'
        '<node id="d" x="0" y="80"/><node id="in" x="-200" y="0"/>',
        '<edge id="ab" from="a" to="b" numLanes="1" speed="14"/>'
        '<edge id="bc" from="b" to="c" numLanes="1" speed="14"/>'
        '<edge id="cd" from="c" to="d" numLanes="1" speed="14"/>'
        '<edge id="da" from="d" to="a" numLanes="1" speed="14"/>'
        '<edge id="ia" from="in" to="a" numLanes="1" speed="14"/>',
    )
    loop = " ".join(["ab bc cd da"] * 200)
    return config(
        folder,
        f'<route id="circle" edges="ia {loop}"/><route id="ego" edges="ia ab bc"/>'
        '<flow id="f" route="circle" begin="0" end="86400" vehsPerHour="2400" '
        'departSpeed="max"/>',
    )


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    custom = (
        CustomScenario("long", write_long_road(tmp_path_factory.mktemp("long")), "ego"),
        CustomScenario("gridlock", write_gridlock(tmp_path_factory.mktemp("grid")), "ego"),
    )
    sumo = SumoBackend(cache_dir=tmp_path_factory.mktemp("cache"), custom=custom)
    yield sumo
    sumo.close()


def timed_episode(
    backend: SumoBackend, scenario: str, **options: OptionValue
) -> tuple[float, list[float], str]:
    """Reset, then IDM + MOBIL until the end: the reset's wall time, each step's, the reason."""
    info = {s.name: s for s in backend.scenarios()}[scenario]
    start = time.monotonic()
    obs = backend.reset(scenario, 0, {**info.options, **options})
    reset_s = time.monotonic() - start
    driver, steps = IDMMobilDriver(), []
    while not (obs.terminated or obs.truncated):
        start = time.monotonic()
        obs = backend.step(obs.seq + 1, *driver.act(obs))
        steps.append(time.monotonic() - start)
    return reset_s, steps, obs.reason


def test_the_end_of_a_50_km_trip_waits_for_its_leader_no_longer_than_a_step_may_take(
    backend: SumoBackend,
) -> None:
    """The leader-at-entry drives the whole 50 km: the simulation runs on for it until the
    wall-clock bound (`CEILING_WALL_S`), not the hour of traffic its route would take."""
    reset_s, steps, reason = timed_episode(backend, "long", max_episode_time=20.0)
    assert reason == EndReason.TIME_LIMIT
    assert max(steps) < STEP_DEADLINE_S / 2
    assert steps[-1] >= 0.5 * CEILING_WALL_S  # the last reply waited, and stopped waiting
    assert reset_s < 30.0


def test_a_gridlock_ends_the_episode_as_jammed_with_every_reply_in_time(
    backend: SumoBackend,
) -> None:
    reset_s, steps, reason = timed_episode(
        backend, "gridlock", warmup=90.0, jam_patience=20.0, insertion_timeout=300.0
    )
    assert reason == EndReason.JAMMED
    assert max(steps) < STEP_DEADLINE_S / 2 and reset_s < 60.0
