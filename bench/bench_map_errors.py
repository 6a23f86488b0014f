"""A published corner map's errors against the simulator's truth: how honest its stored covariances are and how its
corners' errors correlate with distance (the EKF's ``ekf.map.corr_share`` / ``ekf.map.corr_length_m``).

    .venv/bin/python -m bench.bench_map_errors --root ROOT [--map NAME] [--map-version vNNNN]

The truth corners are moved into the map's frame by geodesy and fitted onto the map corners (the evaluation's
``truth_in_map``); per matched corner the residual, its NEES under the stored 2x2 covariance, and for every pair of
corners the product of their residual vectors, binned by distance and divided by the mean squared residual (a
correlation). The kernel ``share * exp(-d^2 / (2 length^2))`` is fitted to the bins under ``--fit-max-m`` (beyond it the
rigid fit's own removal of a shared offset and rotation shows as a negative correlation).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

BINS_M = (0.0, 15.0, 40.0, 80.0, 150.0, 300.0, 1e9)
MIN_FIT_PAIRS = 50  # a kernel from fewer pairs says nothing (a tiny city's 4 corners give 6)


def residuals(root: Path, name: str | None, version: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(matched map corners (M,2), their residuals against the fitted truth (M,2), stored covariances (M,2,2))."""
    from scipy.spatial import cKDTree

    from bench.roots import simulator_dir
    from mapformat.loader import open_map
    from stages.evaluate.metrics import align_truth_to_map
    from stages.evaluate.params import parse_reference_frame
    from stages.evaluate.reference import read_reference, read_truth_corners

    maps = sorted(p for p in (root / "maps").iterdir() if p.is_dir())
    folder = root / "maps" / name if name else maps[0]
    reader = open_map(folder if version == "LATEST" else folder / version)
    table = reader.all_corners()
    en = np.column_stack([table["east_m"].to_numpy(), table["north_m"].to_numpy()])
    cov = reader.covariances(table)
    truth_file = next((simulator_dir(root) / "truth").glob("drive_*_poses_tum.txt"))
    ref = read_reference(truth_file, reader.origin, parse_reference_frame("auto"))
    truth = read_truth_corners(truth_file, ref.T_map_origin_ref)
    fit = align_truth_to_map(en, truth)
    if fit is None:
        raise SystemExit(f"{folder}: fewer than 3 map corners match a true one")
    R, t, _ = fit
    moved = truth @ R.T + t
    d, j = cKDTree(moved).query(en)
    ok = d < 1.0
    return en[ok], en[ok] - moved[j[ok]], cov[ok]


def pair_correlation(en: np.ndarray, r: np.ndarray, bins=BINS_M) -> list[tuple[float, float, int, float]]:
    """Per distance bin (lo, hi, pairs, correlation of the residual vectors)."""
    iu = np.triu_indices(len(en), 1)
    dist = np.linalg.norm(en[iu[0]] - en[iu[1]], axis=1)
    dots = np.einsum("ni,ni->n", r[iu[0]], r[iu[1]])
    var = float(np.mean(np.sum(r**2, axis=1)))
    out = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = (dist >= lo) & (dist < hi)
        out.append((lo, hi, int(m.sum()), float(np.mean(dots[m]) / var) if m.sum() else float("nan")))
    return out


def fit_kernel(en: np.ndarray, r: np.ndarray, max_m: float) -> tuple[float, float]:
    """(share, length_m) of share * exp(-d^2 / (2 length^2)) fitted by least squares to the pair products under
    max_m."""
    from scipy.optimize import least_squares

    iu = np.triu_indices(len(en), 1)
    dist = np.linalg.norm(en[iu[0]] - en[iu[1]], axis=1)
    dots = np.einsum("ni,ni->n", r[iu[0]], r[iu[1]]) / np.mean(np.sum(r**2, axis=1))
    m = dist < max_m
    res = least_squares(lambda p: p[0] * np.exp(-0.5 * (dist[m] / p[1]) ** 2) - dots[m], x0=[0.5, 50.0],
                        bounds=([0.0, 1.0], [0.99, 1000.0]))
    return float(res.x[0]), float(res.x[1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True, nargs="+", help="one or more roots (pooled for the fit)")
    ap.add_argument("--map", default=None)
    ap.add_argument("--map-version", dest="version", default="LATEST", help="LATEST, vNNNN or N")
    ap.add_argument("--fit-max-m", type=float, default=150.0)
    args = ap.parse_args(argv)
    ens, rs = [], []
    for root in args.root:
        en, r, cov = residuals(root, args.map, args.version)
        nees = np.einsum("ni,ni->n", r, np.linalg.solve(cov, r[..., None])[..., 0])
        print(f"{root}: {len(en)} corners matched; residual {np.sqrt(np.mean(np.sum(r**2, 1))):.4f} m RMS (2-D), "
              f"stored {np.sqrt(np.mean(np.trace(cov, axis1=1, axis2=2))):.4f} m; NEES (2 dof) mean {nees.mean():.2f}, "
              f"{np.mean(nees < 5.991):.2f} under its 0.95 quantile")
        for lo, hi, n, c in pair_correlation(en, r):
            print(f"  pairs {lo:.0f}-{hi:.0f} m: {n}, correlation {c:+.2f}")
        ens.append(en + 1e6 * len(ens))  # roots apart: no cross-root pairs under the fit distance
        rs.append(r / np.sqrt(np.mean(np.sum(r**2, 1))))
    en_all = np.vstack(ens)
    n_pairs = int(np.sum(np.linalg.norm(en_all[:, None] - en_all[None], axis=2)[np.triu_indices(len(en_all), 1)]
                         < args.fit_max_m))
    if n_pairs < MIN_FIT_PAIRS:
        print(f"no kernel fitted: {n_pairs} pairs under {args.fit_max_m:g} m (fewer than {MIN_FIT_PAIRS})")
        return
    share, length = fit_kernel(en_all, np.vstack(rs), args.fit_max_m)
    print(f"fitted kernel ({n_pairs} pairs under {args.fit_max_m:g} m, {len(args.root)} root(s)): share {share:.2f}, "
          f"length {length:.0f} m")


if __name__ == "__main__":
    main()
