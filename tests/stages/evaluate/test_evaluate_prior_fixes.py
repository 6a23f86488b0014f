"""A drive without GNSS is localized from its start pose (or an ENU prior): the filters' 'fixes' come from its
poses_prior rows in the map's frame, a local prior's rows place nothing by themselves."""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from schemas import SCHEMAS
from stages.common.records import PriorPoses
from stages.evaluate.compute import prior_fixes


def _table(rows: list[PriorPoses]) -> pa.Table:
    return pa.concat_tables([pa.table(r.to_columns(), schema=SCHEMAS["poses_prior"]) for r in rows])


def test_the_start_pose_and_an_enu_prior_are_fixes_a_local_prior_is_not():
    ids = np.arange(5)
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = np.arange(5) * 2.0
    c, s = np.cos(0.3), np.sin(0.3)
    T[0, :2, :2] = [[c, -s], [s, c]]
    start = PriorPoses("d", ids[:1], ids[:1] * 100, T[:1], np.array([[0.0, 0.0, 0.0, np.nan, np.nan, 0.01]]),
                       np.array(["map_enu"], object), np.array(["start"], object), np.array([True]))
    local = PriorPoses("d", ids, ids * 100, T, np.tile([0.1, 0.1, 0.1, 0.01, 0.01, 0.01], (5, 1)),
                       np.full(5, "local", object), np.full(5, "prior_file", object), np.ones(5, bool))
    q0, std0 = np.zeros((5, 3)), np.full((5, 3), np.nan)
    q, std, valid = prior_fixes(_table([local, start]), "d", ids, q0, std0)
    assert valid.tolist() == [True, False, False, False, False]
    assert np.allclose(q[0], [0.0, 0.0, 0.3]) and np.allclose(std[0], [0.0, 0.0, 0.01])
    assert np.isnan(q[1:]).all() and np.isnan(q0).sum() == 0  # the inputs are not changed
    enu = PriorPoses("d", ids, ids * 100, T, np.tile([0.2, 0.3, 0.1, 0.01, 0.01, 0.02], (5, 1)),
                     np.full(5, "map_enu", object), np.full(5, "prior_file", object), np.ones(5, bool))
    q, std, valid = prior_fixes(_table([enu]), "d", ids, q0, std0)
    assert valid.all() and np.allclose(q[:, 0], np.arange(5) * 2.0) and np.allclose(std[:, :2], [0.2, 0.3])
