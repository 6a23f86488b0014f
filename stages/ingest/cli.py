"""Stage-specific commands: ``cornermap inspect FILE`` and ``cornermap drive init|check`` (heavy imports inside
the commands)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    from stages.ingest.scan_format_table import DEFAULT_FORMAT_OF_UNKNOWN_SUFFIX as guess
    from stages.ingest.scan_format_table import (
        SCAN_FORMAT_NAMES,
        format_of_file,
        formats_help,
        scan_format,
        suffixes_help,
    )

    fmt_help = f"{formats_help()} (default: from the suffix; {scan_format(guess).suffixes[0]} means {guess})"

    @app.command("inspect")
    def inspect(path: Path = typer.Argument(..., help=f"a scan file ({suffixes_help()})"),
                fmt: str = typer.Option("", "--format", help=fmt_help),
                sensor: str = typer.Option("hdl64e", help="sensor model for rings when the file has none")) -> None:
        """Print a scan file's header, point count, drops and ring coverage.

        Examples:
          cornermap inspect ../shared/data/kitti_raw_0048_city/0000000000.pcd
          cornermap inspect --format nuscenes_bin --sensor hdl32e \
            ../shared/data/nuscenes_hdl32e_sweep/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin
        """
        import numpy as np

        from pipeline.errors import OptionError
        from pipeline.names import suggest
        from stages.ingest.pcd import read_pcd
        from stages.ingest.scan_formats import drop_invalid_points, read_scan
        from stages.ingest.sensors import SENSORS, ring_coverage, rings_from_elevation_voted, rings_from_point_order

        kinds = SCAN_FORMAT_NAMES
        kind = fmt or format_of_file(path.name)
        if kind not in kinds:
            raise OptionError("--format", [f"{kind!r}: expected one of {', '.join(kinds)}{suggest(kind, kinds)}"])
        if sensor not in SENSORS:
            raise OptionError("--sensor", [f"{sensor!r}: expected one of {', '.join(sorted(SENSORS))}"
                                           f"{suggest(sensor, SENSORS)}"])
        if kind == "pcd":
            cloud = read_pcd(path)
            h = cloud.header
            typer.echo(f"PCD {h.encoding}: fields {' '.join(h.fields)}, sizes {h.sizes}, types {''.join(h.types)}, "
                       f"counts {h.counts}, {h.points} points, {cloud.trailing_bytes} trailing bytes")
        points, drops = drop_invalid_points(read_scan(path, kind))
        typer.echo(f"{len(points)} valid points; dropped {drops['nonfinite']} non-finite, {drops['zero']} zero")
        t = points.time_offset_s
        if points.time_unused:
            typer.echo(f"per-point time not used: {points.time_unused}")
        elif t is None or not len(t):
            typer.echo("no per-point time: the scan is not deskewed")
        else:
            typer.echo(f"per-point time {float(t.min()):.6f} .. {float(t.max()):.6f} s from the scan start (deskewed)")
        model = SENSORS[sensor]
        if points.ring is not None:
            ring, source = points.ring, "file"
        elif model.ring_from_order or not model.elevations_deg:
            ring, source = rings_from_point_order(points.x_m, points.y_m, points.z_m,
                                                  elevations_deg=model.elevations_deg or None), "point_order"
        else:
            ring, source = rings_from_elevation_voted(points.x_m, points.y_m, points.z_m, model.elevations_deg)[0], \
                "elevation_table"
        present, missing = ring_coverage(ring, model.n_rings or int(ring.max()) + 1)
        counts = np.bincount(ring[ring >= 0])
        typer.echo(f"rings ({source}): {present} present, missing {missing}; points per ring "
                   f"min {counts.min() if counts.size else 0} max {counts.max() if counts.size else 0}")

    drive_app = typer.Typer(no_args_is_help=True, help="Draft and check drive files (drive.yaml), the contract "
                                                       "between a recorded drive and cornermap: drive init writes "
                                                       "every key with its unit and frame in a comment, drive check "
                                                       "names each problem with the key and what was expected.")
    app.add_typer(drive_app, name="drive")

    @drive_app.command("init")
    def drive_init(folder: Path = typer.Argument(..., help="the recorded drive's folder"),
                   out: Path = typer.Option(None, "--out", help="where to write the draft (default FOLDER/drive.yaml)"),
                   force: bool = typer.Option(False, "--force", help="overwrite an existing file")) -> None:
        """Draft a drive.yaml by inspecting the files: scan format and fields, point counts, a sensor guess from
        the elevation histogram, the CSV column mapping. What could not be inferred is marked TODO or CHECK.

        Example: cornermap drive init runs/sim/drive_0 --out runs/draft.yaml
        """
        from pipeline.errors import ConfigError
        from stages.ingest.drive_init import draft_drive_file

        if not folder.is_dir():
            raise ConfigError("cornermap drive init", [f"{folder}: not a folder"])
        target = out or folder / "drive.yaml"
        if target.exists() and not force:
            raise ConfigError("cornermap drive init", [f"{target} exists; refusing to overwrite (use --force or "
                                                       f"--out)"])
        draft = draft_drive_file(folder, target)  # its paths relative to where it is written
        if draft.outside:
            raise ConfigError("cornermap drive init", [
                f"--out {target}: the drive's files would be outside the drive file's parent folder "
                f"{target.resolve().parent.parent} ({', '.join(draft.outside[:2])}); a drive file's paths may not "
                "leave it (docs/drive-file.md); hint: write the draft in the drive's folder or next to it"])
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text("\n".join(draft.lines) + "\n")
        tmp.replace(target)
        typer.echo(f"wrote {target}" + (f"; {len(draft.todo)} TODO: " + "; ".join(draft.todo) if draft.todo else ""))
        typer.echo(f"next: complete the TODO/CHECK lines, then `cornermap drive check {target}`")

    @drive_app.command("check")
    def drive_check(drive_file: Path = typer.Argument(..., help="drive.yaml"),
                    content: bool = typer.Option(False, "--content", help="Also print the sha256 of every file the "
                                                 "drive file references (reads them all)"),
                    placed: bool = typer.Option(False, "--placed", help="Refuse (exit 3) a drive that nothing places "
                                                "in a map's frame, as a build does (a warning otherwise)")) -> None:
        """Validate a drive file against its files and print a summary (scans, time span, GNSS rate and coverage
        of the scan times, rings per scan, odometry, survey CRS, what places the drive). Exit 1 with every problem
        listed; with --placed, exit 3 when nothing places the drive in a map's frame.

        A drive in a bucket (s3://BUCKET/.../drive.yaml; relative paths resolve in the same bucket; endpoint and
        credentials from the AWS environment) is fetched into the local scratch and checked there.

        Example: cornermap drive check runs/sim/drive_0/drive.yaml
        """
        from pipeline.drive_store import is_uri, local_drive
        from pipeline.errors import ConfigError, CornermapError, DataQualityError
        from pipeline.storage import normalise_uri
        from stages.ingest.drive_check import check_drive

        words = lambda text: text  # noqa: E731 - a local drive's lines as they are
        if is_uri(drive_file):
            from pipeline.storage import drive_copy_dir

            shown = normalise_uri(drive_file)
            bucket = "/".join(shown.split("/", 3)[:3])
            copy = str(drive_copy_dir(bucket))
            words = lambda text: text.replace(copy, bucket)  # noqa: E731 - the bucket's names, not the local copy's
            drive_file = local_drive(drive_file)
        else:
            shown = str(drive_file)
        try:
            result = check_drive(drive_file, content=content)
        except CornermapError as exc:
            if words(str(exc)) == str(exc):
                raise
            if isinstance(exc, DataQualityError):
                raise DataQualityError(words(str(exc))) from exc
            raise ConfigError(shown, [words(str(exc))]) from exc
        for line in result.summary:
            typer.echo(words(line))
        for line in result.warnings:
            typer.echo(f"warning: {words(line)}")
        if result.problems:
            raise ConfigError(shown, [words(p) for p in result.problems])
        if placed:
            from stages.ingest.drive_file import load_drive_file
            from stages.ingest.frame import frame_source

            frame = frame_source(load_drive_file(drive_file))
            if frame.problem:
                raise DataQualityError(f"{frame.problem} ({shown})")
        typer.echo(f"ok: {shown}")
