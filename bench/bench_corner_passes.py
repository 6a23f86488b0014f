"""A corner's extraction error by pass, against the simulator's truth: how much of it a pass's views share, and how
much of that every drive shares (a localizer matching the map's corners with the same extractor never sees it).

    .venv/bin/python -m bench.bench_corner_passes --root ROOT [--rho RHO] [--min-views 10]

Each drive's per-scan corners (``corners_per_scan``) are placed with the drive's *true* poses (no pose error) and
matched to the nearest true corner within ``--match-m``; per true corner and drive, the pass mean's offset from the
true corner (its extraction bias) and the views' scatter about it. Over the corners both drives saw at least
``--min-views`` times:
- the correlation of the two drives' biases and its covariance (the part every drive shares: the extractor's
  vertex against the true one, a bias of the corner itself);
- half the mean squared difference of the two biases, less each pass mean's AR(1) part (``var(a) / n_eff``, ``rho``
  the map's ``pass_lag_one_correlation``): the part a pass's views share that another pass does not, over ``var(a)``
  the ``pass_shared_fraction`` of ``stages/cornermap/aggregate.pass_mean_factor`` a localizer needs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def pass_biases(root: Path, drive: str, match_m: float):
    """(true corners (K,2), per true corner: bias of the pass mean (K,2), view count (K,), views' variance per
    axis about the pass mean (K,)) with the drive's views placed by its true poses, in the map's frame."""
    import pyarrow as pa
    from scipy.spatial import cKDTree

    from bench import roots
    from mapformat.loader import open_map
    from stages.common.drive_tables import select_drives
    from stages.common.records import Trajectory
    from stages.cornermap import compute as cc
    from stages.cornermap.transform import covariance_from_components, transform_to_enu
    from stages.evaluate.params import parse_reference_frame
    from stages.evaluate.reference import read_reference, read_truth_corners

    sim = roots.simulator_dir(root)
    reader = open_map(sorted(p for p in (root / "maps").iterdir() if p.is_dir())[0])
    truth_file = sim / "truth" / f"{drive}_poses_tum.txt"
    ref = read_reference(truth_file, reader.origin, parse_reference_frame("auto"))
    truth_c = read_truth_corners(truth_file, ref.T_map_origin_ref)
    traj = Trajectory.from_tum(truth_file)
    T_true = ref.T_map_origin_ref @ traj.T
    t = select_drives(roots.read(root, "corners_per_scan"), [drive])
    t = t.filter(pa.array(cc._finite_rows(t)))
    col = lambda c: t[c].to_numpy()  # noqa: E731
    st = col("stamp_ns")
    k = np.clip(np.searchsorted(traj.stamp_ns, st), 1, len(traj.stamp_ns) - 1)
    k = np.where(np.abs(traj.stamp_ns[k - 1] - st) < np.abs(traj.stamp_ns[k] - st), k - 1, k)
    T_vl = cc._extrinsics(roots.read(root, "drive_info"), [drive])[np.zeros(len(st), int)]
    obs = transform_to_enu(
        np.column_stack([col("x_m"), col("y_m")]),
        np.column_stack([col("theta1_rad"), col("theta2_rad")]),
        covariance_from_components(col("cov_xx_m2"), col("cov_xy_m2"), col("cov_yy_m2")),
        T_true[k],
        T_vl,
        np.zeros((len(st), 3, 3)),
    )
    d, j = cKDTree(truth_c).query(obs.en_m)
    ok = d < match_m
    r, lab, K = obs.en_m[ok] - truth_c[j[ok]], j[ok], len(truth_c)
    n = np.bincount(lab, minlength=K)
    mean = np.stack([np.bincount(lab, r[:, a], minlength=K) for a in (0, 1)], 1) / np.maximum(n, 1)[:, None]
    sq = np.stack([np.bincount(lab, r[:, a] ** 2, minlength=K) for a in (0, 1)], 1) / np.maximum(n, 1)[:, None]
    var = (sq - mean**2).mean(axis=1) * n / np.maximum(n - 1, 1)
    return truth_c, mean, n, var


def main(argv: list[str] | None = None) -> None:
    from bench import roots
    from stages.cornermap.aggregate import effective_samples

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True, nargs="+", help="roots with two simulated drives")
    ap.add_argument("--drives", nargs=2, default=["drive_0", "drive_1"])
    ap.add_argument("--rho", type=float, default=None, help="the views' lag-1 correlation (default: the map's)")
    ap.add_argument("--min-views", type=int, default=10)
    ap.add_argument("--match-m", type=float, default=0.15)
    args = ap.parse_args(argv)
    for root in args.root:
        rho = args.rho
        if rho is None:
            manifest = json.loads((roots.latest(root, "corner_map") / "_manifest.json").read_text())
            rho = float(manifest["extra"]["cornermap"]["pass_lag_one_correlation"]["rho"])
        (_, a, na, va), (_, b, nb, vb) = (pass_biases(root, d, args.match_m) for d in args.drives)
        both = (na >= args.min_views) & (nb >= args.min_views)
        a, b = a[both], b[both]
        var_a, ar = [], []
        for n, v in ((na[both], va[both]), (nb[both], vb[both])):
            n = n.astype(float)
            ne = effective_samples(n, rho)
            with np.errstate(divide="ignore", invalid="ignore"):  # the scatter's shrinkage undone (as the stage)
                va_ = np.where(ne > 1.0, v * (n - 1) * ne / (n * (ne - 1)), v)
            var_a.append(va_)
            ar.append(va_ / ne)
        var_a, ar = 0.5 * (var_a[0] + var_a[1]), 0.5 * (ar[0] + ar[1])
        pass_only = np.mean((a - b) ** 2, axis=1) / 2 - ar
        common = float(np.mean(a * b))  # per axis: the covariance of the two drives' biases
        print(f"{root}: {int(both.sum())} corners seen >= {args.min_views} times by both drives, rho {rho:.2f}")
        print(
            f"  bias of a pass mean, RMS per axis: {np.sqrt(np.mean(a**2)):.4f} / {np.sqrt(np.mean(b**2)):.4f} m; "
            f"the two drives' biases correlate {np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)):+.2f}"
        )
        print(
            f"  per axis, m^2: views' own var(a) {np.mean(var_a):.2e}, AR(1) part of a pass mean {np.mean(ar):.2e}, "
            f"shared by every drive {common:.2e} ({common / np.mean(var_a):.3f} var(a)), shared by one pass only "
            f"{np.mean(pass_only):+.2e} (pass_shared_fraction {np.mean(pass_only) / np.mean(var_a):+.3f}, median "
            f"per corner {np.median(pass_only / var_a):+.3f})"
        )


if __name__ == "__main__":
    main()
