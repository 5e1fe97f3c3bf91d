"""Driver specs as users write them: ``idm``, ``idm+mobil``, ``sumo`` or a policy file.

* ``idm`` / ``idm:PARAMS.json``: IDM keeping its lane (calibrated parameters from the file);
* ``idm+mobil`` / ``idm+mobil:PARAMS.json``: IDM with MOBIL lane changes and the changes its
  route needs (`agent_client.drivers.mobil`);
* ``sumo``: the simulator's own driver model (the reset option ``ego_driver``; the client only
  watches);
* ``runs/NAME/policy.pt``: a trained policy;
* ``pretrained:NAME``: a policy the project ships (``pretrained:cf``, ``pretrained:cflc``,
  ``pretrained:roads``; `agent_client.drivers.pretrained`, each with a model card).

`load_driver` is the one parser of these specs (drive, evaluate, the baselines, the trainer's
reference); every bad spec is a `UsageError` that names it, before any connection is opened.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from agent_client.drivers import pretrained
from agent_client.drivers.episode import Driver, SimulatorDriver
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.mobil import IDMMobilDriver, MobilParams
from agent_client.errors import UsageError

IDM = "idm"
IDM_PREFIX = "idm:"
IDM_MOBIL = "idm+mobil"
IDM_MOBIL_PREFIX = "idm+mobil:"
SIMULATOR = "sumo"
"""The simulator's own driver (SUMO's; highway-env accepts the name for its own)."""
MODELS = (IDM, IDM_MOBIL, SIMULATOR)
"""The driver specs that are models rather than files (``idm:FILE`` and ``idm+mobil:FILE``
take calibrated IDM parameters)."""


def is_model(spec: str) -> bool:
    """True for the model drivers: ``idm``, ``idm+mobil`` (with or without a parameter file)
    and ``sumo``: the specs that are no policy file."""
    return spec in MODELS or spec.startswith((IDM_PREFIX, IDM_MOBIL_PREFIX))


def load_driver(spec: str) -> Driver:
    """A driver from a spec: ``idm``, ``idm+mobil`` (each also ``...:FILE.json``, calibrated
    IDM parameters), ``sumo`` or a policy file."""
    if spec == IDM:
        return IDMDriver()
    if spec.startswith(IDM_PREFIX):
        return IDMDriver(load_idm_params(Path(spec[len(IDM_PREFIX) :])))
    if spec == IDM_MOBIL:
        return IDMMobilDriver()
    if spec.startswith(IDM_MOBIL_PREFIX):
        path = Path(spec[len(IDM_MOBIL_PREFIX) :])
        return IDMMobilDriver(load_idm_params(path), load_mobil_params(path))
    if spec == SIMULATOR:
        return SimulatorDriver()
    path = policy_path(spec)
    if not path.is_file():
        raise UsageError(
            f"driver {spec!r}: no such file; give idm, idm+mobil, sumo (each idm one also "
            "with :PARAMS.json), a policy file (runs/NAME/policy.pt) or pretrained:NAME "
            f"({', '.join(pretrained.names()) or 'none shipped'})"
        )
    from agent_client.drivers.policy import load_policy_driver

    try:
        return load_policy_driver(path)
    except ValueError as exc:
        raise UsageError(f"driver {spec!r}: {exc}") from exc


def policy_path(spec: str) -> Path:
    """The file a policy spec names: a path, or a shipped policy's (``pretrained:NAME``; a
    name that is not shipped gives a path that does not exist)."""
    if spec.startswith(pretrained.PREFIX):
        name = spec.removeprefix(pretrained.PREFIX)
        return pretrained.policy_file(name) or Path(f"<no shipped policy {name!r}>")
    return Path(spec)


def load_mobil_params(path: Path) -> MobilParams:
    """MOBIL's parameters from the ``mobil`` map of an ``idm+mobil:FILE.json`` (its defaults
    where the file has none): ``{"params": {"T": 0.8}, "mobil": {"politeness": 0.0}}``."""
    data: Any = json.loads(path.read_text())  # read (and checked) by load_idm_params first
    mobil = data.get("mobil", {}) if isinstance(data, dict) else {}
    known = [f.name for f in dataclasses.fields(MobilParams)]
    if not isinstance(mobil, dict) or set(mobil) - set(known):
        unknown = sorted(set(mobil) - set(known)) if isinstance(mobil, dict) else ["mobil"]
        raise UsageError(
            f"idm+mobil:{path}: unknown MOBIL parameter {unknown[0]!r}; known: {', '.join(known)}"
        )
    return MobilParams(**mobil)


def load_idm_params(path: Path) -> IDMParams:
    """IDM parameters from a JSON file: `calibrate-idm`'s output or a plain parameter map."""
    try:
        data: Any = json.loads(path.read_text())
    except OSError as exc:
        raise UsageError(f"idm:{path}: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise UsageError(f"idm:{path}: not JSON: {exc}") from exc
    params = data.get("params", data) if isinstance(data, dict) else None
    if isinstance(params, dict) and params is data:
        params = {k: v for k, v in params.items() if k != "mobil"}
    known = [f.name for f in dataclasses.fields(IDMParams)]
    if not isinstance(params, dict):
        raise UsageError(f"idm:{path}: expected a map of IDM parameters ({', '.join(known)})")
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise UsageError(
            f"idm:{path}: unknown IDM parameter {unknown[0]!r}; known: {', '.join(known)}"
        )
    return IDMParams(**params)


def training_settings(spec: str) -> tuple[str | list[str] | None, dict[str, Any]]:
    """The scenario (or scenarios) and reset options a policy file was trained with, from its
    run's config.json.

    A policy trained with ``decision_interval`` 1.0 must also drive with it; drive and evaluate
    use these as defaults (the command line overrides them). ``(None, {})`` for the model
    drivers and policies without a run folder.
    """
    if is_model(spec):
        return None, {}
    if spec.startswith(pretrained.PREFIX):
        saved = pretrained.settings(spec.removeprefix(pretrained.PREFIX))
        if not saved:
            return None, {}
    else:
        config = Path(spec).parent / "config.json"
        if not config.is_file():
            return None, {}
        saved = json.loads(config.read_text())
    options = {"decision_interval": saved.get("decision_interval", 0.1)}
    options.update(saved.get("scenario_options") or {})
    return saved.get("scenario"), options


def trained_on(trained: str | list[str] | None, scenario: str) -> bool:
    """Whether `scenario` is (one of) the scenario(s) a policy was trained on."""
    return scenario == trained or (isinstance(trained, list) and scenario in trained)
