"""Corner map text in the layout of Im, Im & Jee 2016, Table 1 (shared by every stage that exports it).

One line per corner, tab-separated: index, east (m), north (m), direction angle 1 (deg), direction angle 2
(deg), then the 2x2 covariance row-major (m^2: ee en ne nn). Lines starting with ``#`` are comments; the first
line is a header naming the columns. Positions carry millimetres, angles hundredths of a degree, covariances
three significant digits.

With an origin, comment lines before the column header state the frame so the numbers can be placed on Earth:
``# frame: ENU (east, north, up) ...``, ``# origin: lat_deg=... lon_deg=... h_m=... (WGS84, ellipsoidal)``,
``# units: ...``; ``parse_frame_header`` reads the origin back.
"""
from __future__ import annotations

import io
import re

import numpy as np

from pipeline.errors import FormatError

_ORIGIN_RE = re.compile(r"^#\s*origin:\s*lat_deg=(\S+)\s+lon_deg=(\S+)\s+h_m=(\S+)")

HEADER = ("# Index\tEast (m)\tNorth (m)\tDirection Angle 1 (deg)\tDirection Angle 2 (deg)\t"
          "Covariance Matrix (2x2, m^2: ee en ne nn)")
COLUMNS = ("corner_id", "east_m", "north_m", "theta1_rad", "theta2_rad", "cov_ee_m2", "cov_en_m2", "cov_nn_m2")
_FMT = ["%d", "%.3f", "%.3f", "%.2f", "%.2f", "%.2e", "%.2e", "%.2e", "%.2e"]


def format_im2016_text(corner_id: np.ndarray, east_m: np.ndarray, north_m: np.ndarray, theta1_rad: np.ndarray,
                       theta2_rad: np.ndarray, cov_ee_m2: np.ndarray, cov_en_m2: np.ndarray,
                       cov_nn_m2: np.ndarray, origin: dict[str, float] | None = None) -> str:
    """Columns of a corner map -> Table 1 text (header line included).

    ``origin`` ({lat_deg, lon_deg, h_m}, WGS84): the map's ENU origin, written as frame comment lines first.
    """
    cols = [np.asarray(corner_id, float), east_m, north_m, np.degrees(theta1_rad), np.degrees(theta2_rad),
            cov_ee_m2, cov_en_m2, cov_en_m2, cov_nn_m2]
    buf = io.StringIO()
    if origin is not None:
        buf.write(frame_header(origin))
    buf.write(HEADER + "\n")
    if len(cols[0]):
        np.savetxt(buf, np.column_stack([np.asarray(c, float) for c in cols]), fmt=_FMT, delimiter="\t")
    return buf.getvalue()


def frame_header(origin: dict[str, float]) -> str:
    """Comment lines naming the frame, the WGS84 origin (1e-9 deg, 0.1 mm) and the units."""
    return ("# frame: local ENU (east, north, up) tangent plane about the origin below; angles counter-clockwise "
            "from east\n"
            f"# origin: lat_deg={float(origin['lat_deg']):.9f} lon_deg={float(origin['lon_deg']):.9f} "
            f"h_m={float(origin['h_m']):.4f} (WGS84, ellipsoidal height)\n"
            "# units: east/north m, angles deg, covariance m^2\n")


def parse_frame_header(text: str) -> dict[str, float] | None:
    """The origin stated by ``frame_header`` in ``text`` ({lat_deg, lon_deg, h_m}), or None when absent."""
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        m = _ORIGIN_RE.match(line)
        if m:
            return {"lat_deg": float(m.group(1)), "lon_deg": float(m.group(2)), "h_m": float(m.group(3))}
    return None


def parse_im2016_text(text: str, *, source: str = "<text>") -> dict[str, np.ndarray]:
    """Table 1 text -> columns named as COLUMNS (angles in radians). Raises FormatError naming the line."""
    lines = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1)
             if ln.strip() and not ln.strip().startswith("#")]
    if not lines:
        return {name: np.empty(0, np.int64 if name == "corner_id" else float) for name in COLUMNS}
    rows = np.empty((len(lines), 9))
    for r, (lineno, line) in enumerate(lines):
        fields = line.replace("\u2212", "-").split()
        if len(fields) != 9:
            raise FormatError(f"{source} line {lineno}: expected 9 fields (index east north angle1 angle2 "
                              f"cov_ee cov_en cov_ne cov_nn), got {len(fields)}: {line[:80]!r}")
        try:
            rows[r] = [float(v) for v in fields]
        except ValueError as exc:
            raise FormatError(f"{source} line {lineno}: not a number in {line[:80]!r}") from exc
    bad = ~np.isfinite(rows).all(axis=1)
    asym = np.abs(rows[:, 6] - rows[:, 7]) > 1e-9 + 1e-6 * np.abs(rows[:, 6:8]).max(axis=1)
    not_pd = (rows[:, 5] <= 0.0) | (rows[:, 8] <= 0.0) | (rows[:, 5] * rows[:, 8] - rows[:, 6] * rows[:, 7] <= 0.0)
    for mask, what in ((bad, "non-finite value"), (asym, "covariance not symmetric (en != ne)"),
                       (not_pd, "covariance is not positive definite")):
        if mask.any():
            lineno = lines[int(np.argmax(mask))][0]
            raise FormatError(f"{source} line {lineno}: {what}")
    out = {name: rows[:, c] for c, name in enumerate(("corner_id", "east_m", "north_m"))}
    out["corner_id"] = rows[:, 0].astype(np.int64)
    out["theta1_rad"], out["theta2_rad"] = np.radians(rows[:, 3]), np.radians(rows[:, 4])
    out["cov_ee_m2"], out["cov_en_m2"], out["cov_nn_m2"] = rows[:, 5], rows[:, 6], rows[:, 8]
    return out
