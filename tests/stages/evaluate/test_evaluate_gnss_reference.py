"""``cornermap evaluate --reference gnss``: the drive's own GNSS/INS fixes (gnss_enu, the map's frame) written as a
TUM reference that states its frame, read back by the evaluation's reference reader onto the same poses."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from pipeline.errors import ConfigError
from schemas import SCHEMAS
from stages.common.geodesy import EnuOrigin
from stages.evaluate.cli import _gnss_reference_file
from stages.evaluate.reference import read_reference

ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)


def _gnss(n: int, drive: str = "d") -> pa.Table:
    t = np.arange(n)
    return pa.table({"drive": [drive] * n, "stamp_ns": 1_143_272_000_000_000_000 + t * 10_000_000,
                     "east_m": 0.3 * t, "north_m": 0.1 * t, "up_m": np.full(n, 1.5),
                     "roll_rad": np.full(n, np.nan), "pitch_rad": np.full(n, np.nan),
                     "yaw_enu_rad": np.full(n, 0.25), "std_east_m": np.ones(n), "std_north_m": np.ones(n),
                     "std_up_m": np.ones(n), "std_yaw_rad": np.ones(n)}, schema=SCHEMAS["gnss_enu"])


def test_gnss_reference_round_trips_in_the_maps_frame(tmp_path):
    path = _gnss_reference_file(_gnss(50), "d", ORIGIN, tmp_path)
    ref = read_reference(path, ORIGIN, "auto")
    assert ref.frame == "stated"
    assert ref.q[:, 0] == pytest.approx(0.3 * np.arange(50), abs=1e-6)
    assert ref.q[:, 2] == pytest.approx(np.full(50, 0.25), abs=1e-9)
    assert np.diff(ref.stamps_ns) == pytest.approx(np.full(49, 10_000_000), abs=1000)


def test_a_drive_without_fixes_is_one_named_error(tmp_path):
    with pytest.raises(ConfigError, match="--reference gnss: the drive has no GNSS/INS fix"):
        _gnss_reference_file(_gnss(3, "other"), "d", ORIGIN, tmp_path)
