"""Driver specs: IDM + MOBIL with parameters of its own (a baseline tuned by hand)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agent_client.drivers.mobil import IDMMobilDriver, MobilParams
from agent_client.drivers.spec import load_driver
from agent_client.errors import UsageError

ROOT = Path(__file__).resolve().parents[3]


def test_idm_mobil_takes_mobil_parameters_from_its_file(tmp_path: Path) -> None:
    driver = load_driver(f"idm+mobil:{ROOT / 'configs' / 'idm-mobil-selfish.json'}")
    assert isinstance(driver, IDMMobilDriver)
    assert driver.params.T == 0.8 and driver.mobil.politeness == 0.0
    assert driver.mobil.threshold == MobilParams().threshold  # the rest stays MOBIL's default
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps({"T": 1.0, "mobil": {"threshold": 0.5}}))
    driver = load_driver(f"idm+mobil:{plain}")
    assert isinstance(driver, IDMMobilDriver)
    assert driver.params.T == 1.0 and driver.mobil.threshold == 0.5


def test_an_unknown_mobil_parameter_is_named(tmp_path: Path) -> None:
    typo = tmp_path / "typo.json"
    typo.write_text(json.dumps({"params": {}, "mobil": {"politness": 0.0}}))
    with pytest.raises(UsageError, match="politness"):
        load_driver(f"idm+mobil:{typo}")
