"""The bare corner EKF the filter's oracle tests run: the paper's ICP-only motion with fixed noise, no gyro bias
state, no road markings, every look at a corner counting fully. The stage's defaults (``EkfConfig()``) add those
parts; a test that checks the filter's core against a known truth states the bare settings here."""

from __future__ import annotations

from typing import Any

from stages.evaluate.ekf_params import EkfConfig

BARE: dict[str, dict[str, Any]] = {
    "icp": {"sigma_frac": 0.02, "sigma_xy_m": 0.01, "sigma_yaw_deg": 0.05, "sigma_yaw_frac": 0.02,
            "gyro_bias_state": False, "gyro_fusion": False, "gyro_gate": False},
    "corners": {"range_sigma_floor_m": 0.02, "bearing_sigma_floor_deg": 0.1, "decorrelation_m": 0.0},
    "markings": {"enabled": False, "map_sigma_m": 0.0, "map_sigma_deg": 0.0},
}


def bare_ekf(**sections: dict[str, Any]) -> EkfConfig:
    """The bare EKF with some fields of some sections changed: ``bare_ekf(corners={"sensor_range_m": 40.0})``."""
    unknown = set(sections) - set(EkfConfig.model_fields)
    if unknown:
        raise KeyError(f"bare_ekf: no section {sorted(unknown)}")
    return EkfConfig.model_validate({name: {**BARE.get(name, {}), **values} if isinstance(values, dict) else values
                                     for name, values in {**BARE, **sections}.items()})
