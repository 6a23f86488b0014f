"""The corner map as text in the layout of Im et al. 2016 Table 1, and its parser (round trip).

One line per corner, tab-separated: index, east (m), north (m), direction angle 1 (deg), direction angle 2
(deg), then the 2x2 covariance row-major (m^2: ee en ne nn). Lines starting with ``#`` are comments; the first
line is a header naming the columns. Positions carry millimetres, angles hundredths of a degree, covariances
three significant digits (a rounded covariance is still positive definite: the parser checks).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from pipeline.errors import FormatError

HEADER = ("# Index\tEast (m)\tNorth (m)\tDirection Angle 1 (deg)\tDirection Angle 2 (deg)\t"
          "Covariance Matrix (2x2, m^2: ee en ne nn)")
COLUMNS = ("corner_id", "east_m", "north_m", "theta1_rad", "theta2_rad", "cov_ee_m2", "cov_en_m2", "cov_nn_m2")


def _column(table, name: str) -> np.ndarray:
    if hasattr(table, "column"):  # pyarrow.Table
        return table.column(name).to_numpy()
    return np.asarray(table[name])


def format_im2016_text(table) -> str:
    """corner_map table (pyarrow.Table or mapping of columns) -> text in the paper's Table 1 layout."""
    cols = {name: _column(table, name) for name in COLUMNS}
    a1 = np.degrees(cols["theta1_rad"])
    a2 = np.degrees(cols["theta2_rad"])
    lines = [HEADER]
    for i, e, n, t1, t2, cee, cen, cnn in zip(cols["corner_id"], cols["east_m"], cols["north_m"], a1, a2,
                                              cols["cov_ee_m2"], cols["cov_en_m2"], cols["cov_nn_m2"]):
        lines.append(f"{int(i)}\t{e:.3f}\t{n:.3f}\t{t1:.2f}\t{t2:.2f}\t{cee:.2e}\t{cen:.2e}\t{cen:.2e}\t{cnn:.2e}")
    return "\n".join(lines) + "\n"


def parse_im2016_text(text: str, *, source: str = "<text>") -> Mapping[str, np.ndarray]:
    """Text in the Table 1 layout -> columns of COLUMNS (angles back in radians). Raises FormatError."""
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != 9:
            raise FormatError(f"{source} line {lineno}: expected 9 fields (index east north angle1 angle2 "
                              f"cov_ee cov_en cov_ne cov_nn), got {len(fields)}: {stripped[:80]!r}")
        try:
            index = int(fields[0])
            values = [float(v.replace("\u2212", "-")) for v in fields[1:]]
        except ValueError as exc:
            raise FormatError(f"{source} line {lineno}: not a number in {stripped[:80]!r}; hint: the index is an "
                              "integer, the other 8 fields are decimal numbers") from exc
        e, n, a1, a2, cee, cen, cne, cnn = values
        if not np.all(np.isfinite(values)):
            raise FormatError(f"{source} line {lineno}: non-finite value in {stripped[:80]!r}")
        if abs(cen - cne) > 1e-9 + 1e-6 * max(abs(cen), abs(cne)):
            raise FormatError(f"{source} line {lineno}: covariance not symmetric: en {cen} != ne {cne} m^2")
        if cee <= 0.0 or cnn <= 0.0 or cee * cnn - cen * cne <= 0.0:
            raise FormatError(f"{source} line {lineno}: covariance [[{cee}, {cen}], [{cne}, {cnn}]] m^2 is not "
                              "positive definite")
        rows.append((index, e, n, np.radians(a1), np.radians(a2), cee, cen, cnn))
    if not rows:
        return {name: np.empty(0, np.int64 if name == "corner_id" else float) for name in COLUMNS}
    arr = list(zip(*rows))
    out = {name: np.asarray(arr[c], dtype=float) for c, name in enumerate(COLUMNS)}
    out["corner_id"] = out["corner_id"].astype(np.int64)
    return out
