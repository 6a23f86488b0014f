"""The Table 1 text layout: round trip, the paper's own rows parse, malformed text gives FormatError."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from pipeline.errors import FormatError
from schemas import SCHEMAS
from stages.cornermap.export import format_im2016_text, parse_im2016_text


def _table(n: int, seed: int) -> pa.Table:
    rng = np.random.default_rng(seed)
    a = rng.normal(0, 0.05, (n, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(2)
    theta = rng.uniform(-np.pi, np.pi, (n, 2))
    return pa.Table.from_pydict({
        "corner_id": np.arange(1, n + 1), "east_m": rng.uniform(-5000, 5000, n), "north_m": rng.uniform(-5000, 5000, n),
        "theta1_rad": theta[:, 0], "theta2_rad": theta[:, 1],
        "cov_ee_m2": cov[:, 0, 0], "cov_en_m2": cov[:, 0, 1], "cov_nn_m2": cov[:, 1, 1],
        "n_obs": np.full(n, 10), "n_drives": np.full(n, 1, np.int32), "drives": ["d0"] * n,
        "first_seen_ns": np.zeros(n, np.int64), "last_seen_ns": np.ones(n, np.int64),
        "interior_angle_rad": np.full(n, np.pi / 2), "convex": np.ones(n, bool),
    }, schema=SCHEMAS["corner_map"])


def test_round_trip_within_printed_precision():
    table = _table(300, seed=31)
    text = format_im2016_text(table)
    back = parse_im2016_text(text)
    np.testing.assert_array_equal(back["corner_id"], table["corner_id"].to_numpy())
    np.testing.assert_allclose(back["east_m"], table["east_m"].to_numpy(), atol=5e-4)
    np.testing.assert_allclose(back["theta1_rad"], table["theta1_rad"].to_numpy(), atol=np.radians(0.005) + 1e-12)
    np.testing.assert_allclose(back["cov_en_m2"], table["cov_en_m2"].to_numpy(), rtol=5e-3)
    assert len(text.encode()) / 300 < 90, "bytes per corner: the size target needs < ~100"


def test_the_papers_table_1_rows_parse():
    text = ("1\t10\t10\t132\t45\t0.0021\t0.0009\t0.0009\t0.0029\n"
            "2\t20\t30\t\u221213\t\u221213\t0.0042\t\u22120.001\t\u22120.001\t0.0015\n")
    back = parse_im2016_text(text)
    np.testing.assert_allclose(np.degrees(back["theta1_rad"]), [132, -13])
    np.testing.assert_allclose(back["cov_en_m2"], [0.0009, -0.001])


@pytest.mark.parametrize("line, match", [
    ("1\t10\t10\t132\t45\t0.0021\t0.0009\t0.0009", "expected 9 fields"),
    ("1\t10\tten\t132\t45\t0.0021\t0.0009\t0.0009\t0.0029", "not a number"),
    ("1\t10\t10\t132\t45\t0.0021\t0.0009\t0.0008\t0.0029", "not symmetric"),
    ("1\t10\t10\t132\t45\t0.0021\t0.01\t0.01\t0.0029", "not positive definite"),
    ("1\t10\tnan\t132\t45\t0.0021\t0.0009\t0.0009\t0.0029", "non-finite"),
])
def test_malformed_lines_name_the_line(line, match):
    with pytest.raises(FormatError, match=f"map.txt line 2: .*{match}|map.txt line 2: {match}"):
        parse_im2016_text("# header\n" + line + "\n", source="map.txt")
