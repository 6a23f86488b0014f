"""drive init on the other real samples (read in place): a nuScenes HDL-32E sweep and Amsterdam survey tiles."""
from __future__ import annotations

import pytest

from stages.ingest.drive_init import draft_drive_file

pytestmark = pytest.mark.realdata


def test_nuscenes_sweep_is_recognised(shared_data):
    text = "\n".join(draft_drive_file(shared_data / "nuscenes_hdl32e_sweep").lines)
    for expected in ("format: nuscenes_bin", "sensor: hdl32e", "source: filename_us", "ring field present"):
        assert expected in text, (expected, text)


def test_georeferenced_las_tiles_are_drafted_as_a_survey_not_as_scans(shared_data):
    draft = draft_drive_file(shared_data / "amsterdam_mls_laz")
    text = "\n".join(draft.lines)
    assert "survey:" in text and "file: 2292_9700.laz" in text
    assert any("georeferenced clouds" in t for t in draft.todo) and any("CRS" in t for t in draft.todo)
