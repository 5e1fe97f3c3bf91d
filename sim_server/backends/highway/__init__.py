"""highway-env (Farama's highway simulator) behind the bridge: the same protocol, another simulator.

`sim-server --backend highway` serves ``cf`` (one lane) and ``cflc`` (three lanes) on a 2 km
straight road at 80 km/h, and the corridors ``merge`` (the ego enters from an on-ramp), ``exit``
(its route leaves by an off-ramp on the right) and ``lanedrop`` (three lanes become two), whose
geometry is drawn from the seed from the SUMO corridors' grids (`sumo.corridors`: the same seed
draws the same lengths and lanes on both servers). Every road is populated with highway-env's own
human drivers (`IDMVehicle`: IDM car following, MOBIL lane changing). highway-env's gym actions
cannot express the protocol's action, so the scene is built with highway-env's own API, as
``HighwayEnv._create_vehicles`` and ``MergeEnv._make_road`` do, and advanced with ``road.act()``
and ``road.step(dt)``, the two calls of ``AbstractEnv._simulate``, at 10 Hz: the SUMO server's
0.1 s and 1.0 s decision intervals are then whole numbers of steps. The client's ego keeps
highway-env's lateral controller (lane keeping and lane changes) and gets the commanded
acceleration. How each part of the protocol maps onto highway-env, and where it differs from
SUMO: docs/backends.md.

The road ahead (protocol 1.6, `Road` on every observation) is read off highway-env's road network
along the egos' route (`road.Layout`): where each lane stops leading on, and which lanes of the
ego's road lead farthest. A lane that ends is also a standing obstacle for highway-env's humans
(as in ``MergeEnv``), which they do not collide with. An ego whose front passes the end of its
lane (an acceleration lane it did not leave, a dropped lane, a lane past the exit it had to take)
ends there at once with ``lane_end``: highway-env would carry it on along a lane that does not
exist.

Many egos (protocol 1.4, a reset naming ``egos`` > 1, at most `MAX_HIGHWAY_EGOS`): highway-env's
own multi-agent placement (``controlled_vehicles``: each controlled vehicle followed by its share
of the humans; on ``merge`` the egos one after another on the ramp), driven as the one ego is,
each alone (`egos.Driven`); ids ``ego.0``, ``ego.1``, ... in the order of highway-env's
``controlled_vehicles`` (rearmost first). An ego whose drive ends is reported once and removed
from the road. ``egos`` 1 is the one-ego episode under the id ``ego``.

The modules, one job each: `backend.py` (`HighwayBackend`: reset, warm-up, hand-over, the one
ego's steps, the ceiling's run-on), `scenarios.py` (``cf``, ``cflc`` and every scenario offered),
`corridors.py` (``merge``, ``exit``, ``lanedrop`` and their options), `scene.py` (the clock, the
options every scenario shares, a built scene), `networks.py` (the roads, built with highway-env's
API), `placement.py` (the corridors' vehicles), `road.py` (the route and the road ahead),
`simulation.py` (one simulation step and what ends an ego's drive), `lane_changes.py`,
`observation.py`, `egos.py` (the episode's and each ego's book-keeping) and `many.py` (the
decisions of a multi-ego episode).
"""

from sim_server.backends.highway.backend import MAX_HIGHWAY_EGOS, HighwayBackend
from sim_server.backends.highway.corridors import CorridorScenario
from sim_server.backends.highway.scenarios import SCENARIOS, HighwayScenario, Scenario

__all__ = [
    "MAX_HIGHWAY_EGOS",
    "SCENARIOS",
    "CorridorScenario",
    "HighwayBackend",
    "HighwayScenario",
    "Scenario",
]
