"""A small simulation shared by the simulate tests: the tiny city, two drives, 12 scans each."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory):
    from stages.simulate.core import simulate

    out = tmp_path_factory.mktemp("sim_tiny")
    summary = simulate("tiny", 0, out, n_drives=2, scan_limit=12)
    return out, summary
