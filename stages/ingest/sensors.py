"""Spinning-LiDAR sensor models: beam elevation tables and ring (laser index) recovery.

Ring convention: 0 is the lowest beam, increasing upwards (the table index after sorting by elevation).
Three ways to get a point's ring, in order of preference:
1. from the file (a ``ring`` field);
2. from the sensor's elevation table: nearest table elevation to atan2(z, hypot(x, y));
3. from point order (KITTI exports store points laser by laser, each line starting near azimuth 0 and
   running counter-clockwise; a new line starts where atan2(y, x) steps from negative to non-negative).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common import beam_tables


@dataclass(frozen=True)
class SensorModel:
    name: str
    elevations_deg: tuple[float, ...]  # ascending: index = ring
    ring_from_order: bool  # the usual export stores points laser by laser (KITTI HDL-64E)
    label: str = ""  # the maker's name of the model (Ouster: the metadata's ``prod_line``)
    source: str = ""  # where the table comes from (``beam_tables``)

    @property
    def n_rings(self) -> int:
        return len(self.elevations_deg)


def _hdl64e_nominal_deg() -> tuple[float, ...]:
    upper = 2.0 - np.arange(32) / 3.0  # +2.0 .. -8.33 deg, 1/3 deg apart
    lower = -8.83 - 0.5 * np.arange(32)  # -8.83 .. -24.33 deg, 1/2 deg apart
    return tuple(np.round(np.sort(np.concatenate([upper, lower])), 3))


def _model(name: str, table, label: str, source: str, ring_from_order: bool = False) -> SensorModel:
    return SensorModel(name, tuple(sorted(float(v) for v in table)), ring_from_order, label, source)


def _ouster() -> list[SensorModel]:
    """Ouster models: published units' metadata, and the configurations derived from a family's 128-laser table
    (``beam_tables``: U02 every 2nd laser from the lowest, U0 every 4th, BH the lower half, BH02 every 2nd of it)."""
    bt = beam_tables
    derived = "derived from the {0} example ({1})"
    out = [_model("os1-128", bt.OS1_128, "OS-1-128", "ouster-sdk metadata 3_0_1_os-122246000293"),
           _model("os2-128", bt.OS2_128, "OS-2-128", "ouster-sdk metadata OS-2-128-U1_v2.3.0"),
           _model("os1-64", bt.OS1_64_GEN1, "OS-1-64", "ouster-sdk metadata 2_0_0_os1-991913000010-64 (first "
                  "generation, 33.2 deg)"),
           _model("os1-32-gradient", bt.OS1_32_G, "OS-1-32-G", "ouster-sdk metadata OS-1-32-G_v2.1.1"),
           _model("os2-32-uniform", bt.OS2_32_U0, "OS-2-32-U0", "ouster-sdk metadata OS-2-32-U0_v2.0.0")]
    for family, table in (("os1", bt.OS1_128), ("os2", bt.OS2_128)):
        code = family.upper().replace("OS", "OS-")
        for name, label, step, lower in (("64-uniform", "64-U02", 2, False), ("64-below-horizon", "64-BH", 1, True),
                                          ("32-below-horizon", "32-BH02", 2, True)):
            out.append(_model(f"{family}-{name}", bt.lasers_from_lowest(table, step, lower_half=lower),
                              f"{code}-{label}", derived.format(f"{code}-128", label)))
    out.append(_model("os1-32-uniform", bt.lasers_from_lowest(bt.OS1_128, 4), "OS-1-32-U0",
                      derived.format("OS-1-128", "U0")))
    return out


SENSORS: dict[str, SensorModel] = {
    # Velodyne HDL-32E manual: -30.67 .. +10.67 deg in 4/3 deg steps.
    "hdl32e": SensorModel("hdl32e", tuple(np.round(-30.67 + np.arange(32) * (41.34 / 31), 3)), False, "HDL-32E",
                          "Velodyne HDL-32E manual"),
    # Velodyne HDL-64E S2 nominal: two blocks of 32 lasers (per-unit calibration differs by a few 0.1 deg).
    "hdl64e": SensorModel("hdl64e", _hdl64e_nominal_deg(), True, "HDL-64E", "Velodyne HDL-64E S2 nominal"),
    # Velodyne VLP-16: -15 .. +15 deg in 2 deg steps.
    "vlp16": SensorModel("vlp16", tuple(float(v) for v in np.arange(-15.0, 16.0, 2.0)), False, "VLP-16",
                         "Velodyne VLP-16 manual"),
    "vlp32c": _model("vlp32c", beam_tables.VLP32C, "VLP-32C", "VeloView VLP-32c.xml"),
    "pandar64": _model("pandar64", beam_tables.PANDAR64, "Pandar64", "Hesai SDK Pandar64 angle correction file"),
    "pandarxt32": _model("pandarxt32", beam_tables.PANDARXT32, "PandarXT-32", "Hesai SDK pandarXT.h"),
    **{m.name: m for m in _ouster()},
    # Generic: no table unless the drive file gives one (elevations_deg); rings from the file or point order.
    "generic": SensorModel("generic", (), False),
}


def elevation_deg(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.asarray(z, np.float64), np.hypot(x, y)))


def rings_from_elevation(x: np.ndarray, y: np.ndarray, z: np.ndarray,
                         elevations_deg: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """Nearest beam of an ascending elevation table -> int16 ring per point."""
    table = np.asarray(elevations_deg, np.float64)
    if table.size == 0:
        raise ValueError("empty elevation table")
    elev = elevation_deg(x, y, z)
    idx = np.clip(np.searchsorted(table, elev), 1, max(1, table.size - 1))
    if table.size == 1:
        return np.zeros(elev.shape, np.int16)
    lower_closer = (elev - table[idx - 1]) < (table[idx] - elev)
    return (idx - lower_closer).astype(np.int16)


def rings_from_point_order(x: np.ndarray, y: np.ndarray, z: np.ndarray, min_points_per_ring: int = 20,
                           elevations_deg: tuple[float, ...] | np.ndarray | None = None) -> np.ndarray:
    """Rings of a laser-by-laser export: split where azimuth steps from < 0 to >= 0, then rank the lines by
    median elevation so that ring 0 is the lowest. Lines shorter than ``min_points_per_ring`` (spurious
    splits from azimuth jitter at the seam) are merged into the previous line.

    The rank is the ring only when every beam is present. With the sensor's ``elevations_deg`` table and a
    line count that differs from it (a truncated scan holding only the top 53 of 64 beams), the ranked lines
    are placed on the table at the offset that best matches their median elevations (``align_lines_to_table``)."""
    n = len(x)
    if n == 0:
        return np.zeros(0, np.int16)
    azimuth = np.arctan2(y, x)
    starts = np.flatnonzero((azimuth[:-1] < 0) & (azimuth[1:] >= 0)) + 1
    bounds = np.concatenate([[0], starts, [n]])
    keep = np.diff(bounds) >= min_points_per_ring
    keep[0] = True  # the first line always starts at 0
    line_starts = bounds[:-1][keep]
    line_of_point = np.searchsorted(line_starts, np.arange(n), side="right") - 1
    elev = elevation_deg(x, y, z)
    order = np.argsort(line_of_point, kind="stable")
    split_at = np.searchsorted(line_of_point[order], np.arange(1, len(line_starts)))
    medians = np.array([np.median(part) for part in np.split(elev[order], split_at)])
    rank = np.empty(len(medians), np.int64)
    rank[np.argsort(medians, kind="stable")] = np.arange(len(medians))
    if elevations_deg is not None and 0 < len(medians) != len(elevations_deg):
        rank = align_lines_to_table(np.sort(medians), elevations_deg)[rank]
    return rank[line_of_point].astype(np.int16)


def align_lines_to_table(sorted_medians_deg: np.ndarray, elevations_deg: tuple[float, ...] | np.ndarray
                         ) -> np.ndarray:
    """Ring of each line (lines sorted by median elevation, lowest first) when fewer or more lines than beams
    were found. Fewer: the contiguous run of table beams (offset k) whose spacing best matches the lines'
    spacing (least summed |diff(medians) - diff(beams)|), then the least summed |median - beam| among ties.
    Spacing, not absolute elevation, because a unit's calibration differs from the nominal table by a few
    0.1 degree (KITTI: +2.5..-24.9 against +2.0..-24.3), while the 1/3 vs 1/2 degree spacing of the HDL-64E's
    two blocks pins the offset of a scan cut at the top or the bottom. More (spurious splits): each line takes
    its nearest beam."""
    table = np.asarray(elevations_deg, np.float64)
    m = np.asarray(sorted_medians_deg, np.float64)
    if len(m) > len(table):
        return rings_from_elevation(np.ones_like(m), np.zeros_like(m), np.tan(np.radians(m)), table).astype(np.int64)
    offsets = np.arange(len(table) - len(m) + 1)
    spacing = np.array([np.abs(np.diff(m) - np.diff(table[k:k + len(m)])).sum() for k in offsets])
    absolute = np.array([np.abs(m - table[k:k + len(m)]).sum() for k in offsets])
    # Offsets whose spacing fits within 0.1 deg of the best (all of them for an evenly spaced table) are told
    # apart by absolute elevation; one misplaced HDL-64E block boundary costs 1/2 - 1/3 = 0.17 deg.
    near = spacing <= spacing.min() + 0.1
    return np.arange(len(m)) + int(offsets[near][np.argmin(absolute[near])])


def ring_coverage(rings: np.ndarray, n_rings: int) -> tuple[int, list[int]]:
    """(number of distinct rings with points, missing rings in 0..n_rings-1). Ring ids are small: counted with
    ``np.bincount`` (a sort in ``np.unique`` took 0.27 ms of a 45k-point gangnam scan's decoding, 2.6 s of the
    one-drive ingest's decoder thread); ``np.unique`` for ids beyond 4096."""
    valid = rings[rings >= 0]
    if len(valid) and int(valid.max()) <= 4096:
        present = np.flatnonzero(np.bincount(valid))
    else:
        present = np.unique(valid)
    missing = sorted(set(range(n_rings)) - set(present.tolist())) if n_rings else []
    return int(present.size), missing


def rings_from_elevation_voted(x: np.ndarray, y: np.ndarray, z: np.ndarray,
                               elevations_deg: tuple[float, ...] | np.ndarray, min_share: float = 0.5,
                               min_vote_range_m: float = 2.0) -> tuple[np.ndarray, bool]:
    """Elevation-table rings, made robust for organised scans.

    Per point, the nearest table elevation is noisy near the vehicle (beam origins are offset from the
    sensor origin, and motion-compensated exports move near points). When the cloud is organised in firing
    blocks of ``n_rings`` points (count divisible by ``n_rings``), every slot of the block is the same laser:
    each slot takes the majority ring of its points. Used only when every slot has a clear majority
    (``min_share``, counting points beyond ``min_vote_range_m``) and the winners are a permutation of all rings;
    otherwise the per-point result stands.
    Returns (rings, voted).
    """
    per_point = rings_from_elevation(x, y, z, elevations_deg)
    k = len(elevations_deg)
    n = len(per_point)
    if k < 2 or n < 4 * k or n % k:
        return per_point, False
    slot = np.arange(n) % k
    far = np.hypot(x, y) >= min_vote_range_m
    votes = np.bincount(slot[far] * k + per_point[far].astype(np.int64), minlength=k * k).reshape(k, k)
    winners = votes.argmax(axis=1)
    share = votes.max(axis=1) / np.maximum(votes.sum(axis=1), 1)
    if np.all(share >= min_share) and np.array_equal(np.sort(winners), np.arange(k)):
        return winners[slot].astype(np.int16), True
    return per_point, False
