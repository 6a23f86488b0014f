"""Lane-following drives: a loop around a set of blocks, offset into a lane (right-hand traffic), rounded
turns, a speed profile capped at 40 km/h with lateral/longitudinal limits and stops at some crossings,
sampled at 100 Hz. The vehicle frame origin is on the ground directly under the lidar.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.city import LANE_W_M, City

V_MAX_MPS = 40.0 / 3.6
A_LAT_MPS2, A_ACC_MPS2, A_DEC_MPS2 = 1.8, 1.2, 1.8
RATE_HZ = 100.0


@dataclass(frozen=True)
class Trajectory:
    """Ground-truth vehicle states at 100 Hz; time in seconds from the drive start."""

    t_s: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    yaw_enu_rad: np.ndarray  # unwrapped
    speed_mps: np.ndarray
    yaw_rate_radps: np.ndarray
    pitch_rad: np.ndarray
    roll_rad: np.ndarray
    length_m: float
    queue_stops: tuple = ()  # (s_first_stop_m, s_last_stop_m, vehicles_ahead) of each stop-and-go queue

    def sample(self, t_s: np.ndarray) -> np.ndarray:
        """(N,) times -> (N, 5): east, north, yaw_enu_rad, pitch_rad, roll_rad (linear interpolation)."""
        return np.column_stack([np.interp(t_s, self.t_s, a) for a in
                                (self.east_m, self.north_m, self.yaw_enu_rad, self.pitch_rad, self.roll_rad)])


def choose_loop_cells(n_rows: int, n_cols: int, nodes_en: np.ndarray, lap_length_m: float,
                      rng: np.random.Generator) -> set[tuple[int, int]]:
    """Grow a simply connected set of blocks until its boundary is at least ``lap_length_m`` long."""
    cells = {(n_rows // 2, max(0, n_cols // 2 - 1))}
    while _perimeter_m(cells, nodes_en) < lap_length_m:
        cands = sorted({(j + dj, i + di) for j, i in cells for dj, di in ((1, 0), (-1, 0), (0, 1), (0, -1))
                        if 0 <= j + dj < n_rows and 0 <= i + di < n_cols} - cells)
        scored = [(c, _perimeter_m(cells | {c}, nodes_en)) for c in cands if loop_nodes(cells | {c}) is not None]
        if not scored:
            break
        gains = np.array([p for _, p in scored])
        weights = np.exp((gains - gains.max()) / 50.0)
        cells = cells | {scored[rng.choice(len(scored), p=weights / weights.sum())][0]}
    return cells


def _boundary_edges(cells: set[tuple[int, int]]) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    out = []
    for j, i in sorted(cells):
        for nb, a, b in (((j - 1, i), (j, i), (j, i + 1)), ((j, i + 1), (j, i + 1), (j + 1, i + 1)),
                         ((j + 1, i), (j + 1, i + 1), (j + 1, i)), ((j, i - 1), (j + 1, i), (j, i))):
            if nb not in cells:
                out.append((a, b))
    return out


def loop_nodes(cells: set[tuple[int, int]]) -> list[tuple[int, int]] | None:
    """Counter-clockwise boundary nodes (row j, column i) of the cell set, or None if not one simple loop."""
    edges = _boundary_edges(cells)
    nxt: dict = {}
    for a, b in edges:
        if a in nxt:
            return None
        nxt[a] = b
    start = min(nxt)
    loop, node = [start], nxt[start]
    while node != start:
        loop.append(node)
        node = nxt[node]
    return loop if len(loop) == len(edges) else None


def out_and_back_nodes(n_rows: int, n_cols: int, row: int | None = None) -> list[tuple[int, int]]:
    """An out-and-back route (``route: out_and_back``): along the east-west street of node row ``row`` (default the
    middle one) from its west end to its east end and back, a U-turn at each end; as a closed node list (the U-turn
    nodes once each) that ``lane_polyline`` turns into the two legs, each in its own lane of the same street."""
    j = n_rows // 2 if row is None else int(row)
    out = [(j, i) for i in range(n_cols + 1)]
    return out + out[-2:0:-1]


def district_loop(n_rows: int, n_cols: int, k: int) -> list[tuple[int, int]]:
    """Drive ``k``'s route of ``route: districts``: the loop around a window of one block row and two block columns,
    row ``k mod n_rows``, first column ``(k // n_rows) mod (n_cols - 1)``. Drives 0 .. n_rows (n_cols - 1) - 1 sweep
    the grid west to east (each new window shares a street with an earlier one: the map grows district by
    district), later drives revisit the same windows."""
    if n_cols < 2:
        raise ValueError(f"route districts needs 2 or more block columns; got {n_cols}")
    j = k % n_rows
    i = (k // n_rows) % (n_cols - 1)
    loop = loop_nodes({(j, i), (j, i + 1)})
    assert loop is not None
    return loop


def _perimeter_m(cells, nodes_en) -> float:
    return float(sum(np.linalg.norm(nodes_en[b] - nodes_en[a]) for a, b in _boundary_edges(cells)))


def lane_polyline(city: City, loop: list[tuple[int, int]], lane: int) -> tuple[np.ndarray, list[float]]:
    """Closed lane-centre polyline (N, 2) starting mid-segment, and the arc length of each turn's start."""
    pts = np.array([city.nodes_en[n] for n in loop])
    m = len(pts)
    t = np.roll(pts, -1, 0) - pts
    seg_len = np.linalg.norm(t, axis=1)
    t /= seg_len[:, None]
    right = np.column_stack([t[:, 1], -t[:, 0]])
    lanes = np.array([city.lanes_row if loop[k][0] == loop[(k + 1) % m][0] else city.lanes_col for k in range(m)])
    off = (np.minimum(lane, lanes - 1) + 0.5) * LANE_W_M
    corner_pieces = []
    for k in range(m):  # corner at node k between segment k-1 and k
        p1, d1 = pts[k] + right[k - 1] * off[k - 1], t[k - 1]
        p2, d2 = pts[k] + right[k] * off[k], t[k]
        cross = d1[0] * d2[1] - d1[1] * d2[0]
        phi = float(np.arctan2(cross, d1 @ d2))
        if abs(phi) > np.radians(175):  # a U-turn (out-and-back): a left half circle about the node
            centre = pts[k]
            ang0 = np.arctan2(*(p1 - centre)[::-1])
            angs = ang0 + np.linspace(0, np.pi, max(8, int(np.pi * off[k - 1] / 0.5)))
            corner_pieces.append(centre + off[k - 1] * np.column_stack([np.cos(angs), np.sin(angs)]))
            continue
        if abs(phi) < np.radians(3):
            corner_pieces.append(np.array([0.5 * (p1 + p2)]))
            continue
        s = ((p2 - p1)[0] * d2[1] - (p2 - p1)[1] * d2[0]) / cross
        c = p1 + s * d1
        radius = 12.0 if phi > 0 else 7.0
        tan_len = min(radius * np.tan(abs(phi) / 2), 0.4 * min(seg_len[k - 1], seg_len[k]))
        radius = tan_len / np.tan(abs(phi) / 2)
        a = c - d1 * tan_len
        centre = a + np.sign(phi) * np.array([-d1[1], d1[0]]) * radius
        ang0 = np.arctan2(*(a - centre)[::-1])
        angs = ang0 + np.linspace(0, phi, max(4, int(abs(phi) * radius / 0.5)))
        corner_pieces.append(centre + radius * np.column_stack([np.cos(angs), np.sin(angs)]))
    start = 0.5 * (corner_pieces[0][-1] + corner_pieces[1 % m][0])
    poly = [start[None]] + [corner_pieces[(k + 1) % m] for k in range(m)] + [start[None]]
    poly = np.concatenate(poly)
    s_cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    turn_starts = []
    for k in range(m):
        first = corner_pieces[(k + 1) % m][0]
        idx = int(np.argmin(np.linalg.norm(poly - first, axis=1)))
        turn_starts.append(float(s_cum[idx]))
    return poly, sorted(turn_starts)


def plan_drive(poly_en: np.ndarray, turn_starts_m: list[float], laps: int, cruise_mps: float, stop_share: float,
               rng: np.random.Generator, ds_m: float = 0.1, queue_share: float = 0.0) -> Trajectory:
    """Speed profile and 100 Hz states for ``laps`` rounds of a closed lane polyline. A share ``queue_share``
    of the stops are stop-and-go queues: 1-3 vehicles stand ahead, the ego stops at the queue's tail and
    creeps forward one vehicle (6.5-8 m) at a time, 2-6 s per stop, before the final stop at the line."""
    from scipy.ndimage import gaussian_filter1d

    seg = np.linalg.norm(np.diff(poly_en, axis=0), axis=1)
    s_poly = np.concatenate([[0], np.cumsum(seg)])
    lap_len = float(s_poly[-1])
    s = np.arange(0.0, laps * lap_len, ds_m)
    s_lap = s % lap_len
    east, north = np.interp(s_lap, s_poly, poly_en[:, 0]), np.interp(s_lap, s_poly, poly_en[:, 1])
    # A car's path is smooth: round the polyline's 0.5 m facets (sigma 1 m) so that heading and yaw rate are
    # continuous; otherwise the true heading steps by degrees at every facet inside a turn.
    sigma = 1.0 / ds_m
    east, north = gaussian_filter1d(east, sigma, mode="wrap"), gaussian_filter1d(north, sigma, mode="wrap")
    yaw = np.unwrap(np.arctan2(np.gradient(north), np.gradient(east)))
    curv = np.abs(gaussian_filter1d(np.gradient(yaw, ds_m), 5))
    wobble = 1.0 - 0.08 * (1 + np.sin(2 * np.pi * s / rng.uniform(150, 300) + rng.uniform(0, 6.3)))
    v = np.minimum(min(cruise_mps, V_MAX_MPS) * wobble, np.sqrt(A_LAT_MPS2 / np.maximum(curv, 1e-6)))
    stops = []
    for lap in range(laps):
        for ts in turn_starts_m:
            if rng.random() < stop_share and ts - 6.0 > 30.0:
                stops.append((int((lap * lap_len + ts - 6.0) / ds_m), float(rng.uniform(5.0, 25.0))))
    stops, queues = _queue_stops(stops, queue_share, ds_m, rng)
    v[0] = v[-1] = 0.0
    for idx, _ in stops:
        v[idx] = 0.0
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * A_ACC_MPS2 * ds_m))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * A_DEC_MPS2 * ds_m))
    dt = 2 * ds_m / np.maximum(v[:-1] + v[1:], 1e-6)
    t_knots = np.concatenate([[0], np.cumsum(dt)])
    for idx, dwell in sorted(stops, reverse=True):  # dwell: duplicate the knot in time
        t_knots[idx + 1:] += dwell
    stops = sorted(stops)
    ins = [idx + 1 for idx, _ in stops]
    t_knots = np.insert(t_knots, ins, [t_knots[idx] + dwell for idx, dwell in stops])
    s_knots = np.insert(s, ins, [s[idx] for idx, _ in stops])
    t = np.arange(0.0, t_knots[-1], 1.0 / RATE_HZ)
    s_t = np.interp(t, t_knots, s_knots)
    yaw_t = np.interp(s_t, s, yaw)
    speed = np.gradient(s_t, t)
    yaw_rate = np.gradient(yaw_t, t)
    acc = gaussian_filter1d(np.gradient(speed, t), 20)
    pitch = -0.008 * acc
    roll = gaussian_filter1d(0.006 * speed * yaw_rate, 20)
    return Trajectory(t, np.interp(s_t, s, east), np.interp(s_t, s, north), yaw_t, speed, yaw_rate, pitch, roll,
                      float(s[-1]), tuple(queues))


def _queue_stops(stops: list, queue_share: float, ds_m: float, rng: np.random.Generator) -> tuple[list, list]:
    """Stops (sample index, dwell s) with the creeping stops of the queues added, and the queues as
    (s_first_stop_m, s_last_stop_m, vehicles ahead)."""
    if queue_share <= 0:
        return stops, []
    out, queues = list(stops), []
    for idx, _ in stops:
        if rng.random() >= queue_share:
            continue
        n = int(rng.integers(1, 4))
        steps = rng.uniform(6.5, 8.0, n)
        first = idx - int(round(steps.sum() / ds_m))
        if first * ds_m < 20.0:
            continue
        back = np.cumsum(steps[::-1])[::-1]  # distance of each creeping stop behind the final one
        out += [(idx - int(round(b / ds_m)), float(rng.uniform(2.0, 6.0))) for b in back]
        queues.append((first * ds_m, idx * ds_m, n))
    return sorted(out), queues
