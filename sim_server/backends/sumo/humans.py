"""The human drivers of the built-in roads and of a user's map: SUMO vehicle types.

The paper's traffic came from VISSIM, whose drivers follow Wiedemann's model; SUMO has it
(``W99``, Wiedemann 99, the model VISSIM's motorway drivers use) beside its default Krauss, IDM
and the Extended IDM (``EIDM``: IDM with estimation errors and reaction times). An option
(``human_model``) picks one per scenario, so that a policy can be trained among one population
and judged among another. Each keeps SUMO's own default parameters but for the spread of the
desired speeds and Krauss' imperfection, which the scenario's options set.

Source: SUMO docs, "Car-Following-Models" (Krauss, IDM, EIDM, W99 and their parameters).
"""

from __future__ import annotations

HUMAN_MODELS: dict[str, str] = {
    "krauss": "Krauss",
    "idm": "IDM",
    "eidm": "EIDM",
    "w99": "W99",
}
"""Option value (`sim_server.backends.options.HUMAN_MODEL_NAMES`) -> SUMO's
``carFollowModel``."""
TRUCK_TYPE = "truck"


def car_following(model: str, sigma: float) -> str:
    """The car-following attributes of a vType: Krauss with its imperfection `sigma`, the
    others with SUMO's defaults."""
    if model == "krauss":
        return f'carFollowModel="Krauss" sigma="{sigma}"'
    return f'carFollowModel="{HUMAN_MODELS[model]}"'


def human_type(type_id: str, model: str, sigma: float, mean: float, dev: float) -> str:
    """A passenger car's vType line: `model`, desired speeds a truncated normal of `mean` and
    `dev` times the speed limit, LC2013 lane changing."""
    return (
        f'    <vType id="{type_id}" vClass="passenger" {car_following(model, sigma)} '
        f'speedFactor="normc({mean},{dev},0.5,1.5)" lcModel="LC2013"/>\n'
    )


def truck_type(model: str, sigma: float) -> str:
    """A heavy vehicle's vType line: 12 m, at most 90 km/h, slow to accelerate."""
    return (
        f'    <vType id="{TRUCK_TYPE}" vClass="truck" length="12" maxSpeed="25" accel="1.0" '
        f'decel="4.0" {car_following(model, sigma)} speedFactor="normc(0.9,0.05,0.7,1.1)" '
        'lcModel="LC2013" guiShape="truck"/>\n'
    )
