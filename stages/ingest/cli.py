"""Stage-specific commands: ``cornermap ingest inspect FILE`` (heavy imports inside the command)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("inspect")
    def inspect(path: Path = typer.Argument(..., help="a scan file (.pcd, .bin, .las/.laz)"),
                fmt: str = typer.Option("", "--format", help="pcd | kitti_bin | nuscenes_bin | las (default: "
                                                             "from the suffix; .bin means kitti_bin)"),
                sensor: str = typer.Option("hdl64e", help="sensor model for rings when the file has none")) -> None:
        """Print a scan file's header, point count, drops and ring coverage.

        Examples:
          cornermap ingest inspect ../shared/data/kitti_raw_0048_city/0000000000.pcd
          cornermap ingest inspect sweep.pcd.bin --format nuscenes_bin --sensor hdl32e
        """
        import numpy as np

        from stages.ingest.pcd import read_pcd
        from stages.ingest.scan_formats import drop_invalid_points, read_scan
        from stages.ingest.sensors import SENSORS, ring_coverage, rings_from_elevation_voted, rings_from_point_order

        from pipeline.errors import UnknownNameError
        from pipeline.registry import suggest

        name = path.name.lower()
        kind = fmt or ("pcd" if name.endswith(".pcd") else "las" if name.endswith((".las", ".laz")) else "kitti_bin")
        kinds = ("pcd", "kitti_bin", "nuscenes_bin", "las")
        if kind not in kinds:
            raise UnknownNameError(f"--format {kind!r}: expected one of {', '.join(kinds)}{suggest(kind, kinds)}")
        if sensor not in SENSORS:
            raise UnknownNameError(f"--sensor {sensor!r}: expected one of {', '.join(sorted(SENSORS))}"
                                   f"{suggest(sensor, SENSORS)}")
        if kind == "pcd":
            cloud = read_pcd(path)
            h = cloud.header
            typer.echo(f"PCD {h.encoding}: fields {' '.join(h.fields)}, sizes {h.sizes}, types {''.join(h.types)}, "
                       f"counts {h.counts}, {h.points} points, {cloud.trailing_bytes} trailing bytes")
        points, drops = drop_invalid_points(read_scan(path, kind))
        typer.echo(f"{len(points)} valid points; dropped {drops['nonfinite']} non-finite, {drops['zero']} zero")
        model = SENSORS[sensor]
        if points.ring is not None:
            ring, source = points.ring, "file"
        elif model.ring_from_order or not model.elevations_deg:
            ring, source = rings_from_point_order(points.x_m, points.y_m, points.z_m), "point_order"
        else:
            ring, source = rings_from_elevation_voted(points.x_m, points.y_m, points.z_m, model.elevations_deg)[0], \
                "elevation_table"
        present, missing = ring_coverage(ring, model.n_rings or int(ring.max()) + 1)
        counts = np.bincount(ring[ring >= 0])
        typer.echo(f"rings ({source}): {present} present, missing {missing}; points per ring "
                   f"min {counts.min() if counts.size else 0} max {counts.max() if counts.size else 0}")
