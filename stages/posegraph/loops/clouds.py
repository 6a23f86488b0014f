"""The scans a loop (or survey anchor) is verified on: deskewed, voxel-downsampled vehicle-frame clouds of the
wanted poses, loaded in batches (in worker processes when there are several)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from stages.common.registration import crop_range, voxel_downsample
from stages.posegraph.factors.drive import DriveInput, deskew_scan_lidar, increments

# (drive, scan_id) list -> {(drive, scan_id): (points_lidar_m (N,3), time_offset_s (N,) or None)}
ScanLoader = Callable[[list[tuple[str, int]]], dict[tuple[str, int], tuple[np.ndarray, np.ndarray | None]]]


def cloud_requests(offsets: np.ndarray, wanted) -> list[tuple[int, int, int]]:
    """Global pose indices -> the ``(global index, drive index, scan index within the drive)`` triples that
    ``_clouds_item`` loads (``offsets``: each drive's first global index, then the total)."""
    wanted = np.asarray(wanted, np.int64)
    owner = np.searchsorted(offsets, wanted, side="right") - 1
    return [(int(g), int(o), int(g - offsets[o])) for g, o in zip(wanted, owner)]


def vehicle_clouds(drives: list[DriveInput], offsets: np.ndarray, wanted: np.ndarray, load: ScanLoader,
                   voxel_m: float, batch: int = 64, workers: int | None = 1) -> dict[int, np.ndarray]:
    """Deskewed, voxel-downsampled vehicle-frame points of the wanted pose indices, loaded in batches; the
    batches run through ``parallel_map`` (each worker reads its scans from the store) when ``workers`` != 1."""
    from pipeline.parallel import parallel_map

    requests = cloud_requests(offsets, wanted)
    items = [(requests[start:start + batch], voxel_m) for start in range(0, len(requests), batch)]
    out: dict[int, np.ndarray] = {}
    for part in parallel_map(_clouds_item, items, workers=workers if len(items) > 1 else 1,
                             initializer=_use_drives, initargs=(drives, load)):
        out.update(part)
    return out


def _use_drives(drives: list[DriveInput], load: ScanLoader) -> None:
    from pipeline.parallel import set_worker_state

    set_worker_state(drives=drives, load=load, increments={})


def _clouds_item(item) -> dict[int, np.ndarray]:
    """One batch of ``vehicle_clouds`` (module level: a pool process or a cluster worker runs it)."""
    from pipeline.parallel import worker_state

    chunk, voxel_m = item
    state = worker_state()
    drives, incs = state["drives"], state["increments"]
    got = state["load"]([(drives[o].name, int(drives[o].scan_ids[k])) for _, o, k in chunk])
    out = {}
    for g, o, k in chunk:
        d = drives[o]
        pts, toff = got[(d.name, int(d.scan_ids[k]))][:2]
        keep = crop_range(pts, 2.0, 80.0)
        pts = np.asarray(pts, float)[keep]
        if toff is not None and o not in incs:
            incs[o] = increments(d)
        pts = deskew_scan_lidar(d, incs.get(o), k, pts, None if toff is None else np.asarray(toff, float)[keep])
        pts = pts @ d.T_vehicle_lidar[:3, :3].T + d.T_vehicle_lidar[:3, 3]
        out[g] = voxel_downsample(pts, voxel_m)
    return out
