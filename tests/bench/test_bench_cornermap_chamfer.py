"""The corner-map bench's building-corner truth: a chamfered corner's two real vertices, from the truth row of the
walls' intersection (known geometry: a square corner cut 2 m back along each wall)."""
from __future__ import annotations

import numpy as np

from bench.bench_cornermap import chamfer_vertices


def test_chamfer_vertices_are_the_cut_ends_with_the_wall_and_facet_directions(tmp_path):
    (tmp_path / "truth").mkdir()
    (tmp_path / "truth" / "corners.csv").write_text(
        "id,east_m,north_m,theta1_deg,theta2_deg,corner_shape,shape_size_m\n"
        "0,10.0,20.0,0.0,90.0,chamfered,2.000\n"  # walls run east and north from (10, 20)
        "1,0.0,0.0,0.0,90.0,sharp,0.000\n"
        "2,5.0,5.0,0.0,90.0,rounded,3.000\n")
    en, theta = chamfer_vertices(tmp_path)
    np.testing.assert_allclose(en, [[12.0, 20.0], [10.0, 22.0]], atol=1e-12)
    deg = np.degrees(theta)
    np.testing.assert_allclose(deg[0], [0.0, 135.0], atol=1e-9)  # east wall on; facet towards (10, 22)
    np.testing.assert_allclose(deg[1], [90.0, -45.0], atol=1e-9)  # north wall on; facet towards (12, 20)
    # the vertices' interior angle is the chamfer's 135 deg
    assert np.isclose(abs(deg[0][1] - deg[0][0]), 135.0)
