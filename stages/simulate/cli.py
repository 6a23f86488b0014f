"""``cornermap simulate``: generate a synthetic city and drives (heavy imports inside the command)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("simulate", help=(
        "Generate a synthetic city and K drives (HDL-32E PCD scans, INSPVA GNSS/INS CSV, wheel/gyro CSV, "
        "survey LAS, ground truth), deterministic from (preset, seed).\n\n"
        "Examples:\n\n"
        "  cornermap simulate --preset tiny --seed 7 --out runs/sim\n\n"
        "  cornermap simulate --preset gangnam --seed 3 --out runs/gangnam_sim --drives 3 --max-scans 20\n\n"
        "  cornermap simulate --preset demo --out runs/demo_sim --no-motion-distortion --max-scans 50\n\n"
        "  cornermap simulate --preset tiny --seed 7 --drives 3 --changes --out runs/tiny_changed"))(simulate_command)


def simulate_command(
    preset: str = typer.Option("tiny", help="tiny | demo | gangnam"),
    seed: int = typer.Option(0, help="random seed; same preset and seed give identical files"),
    out: Path = typer.Option(..., help="output directory (drive_K/, survey/, truth/)"),
    drives: int = typer.Option(None, help="number of drives (drive 0 maps, later ones evaluate); default 2"),
    motion_distortion: bool = typer.Option(True, help="roll each scan during motion (per-firing poses)"),
    max_scans: int = typer.Option(None, help="cap the scans written per drive (quick looks, tests)"),
    quiet: bool = typer.Option(False, help="no progress bar"),
    changes: bool = typer.Option(False, "--changes", help="the city changes before the last drive (a building "
                                 "demolished, one built, a crosswalk moved); truth in truth/changes.json"),
    changes_from_drive: int = typer.Option(None, help="with --changes: first drive that sees the changed city"),
) -> None:
    from pipeline.errors import DatasetIOError
    from stages.simulate.core import simulate

    if out.exists() and not out.is_dir():
        raise DatasetIOError(f"--out {out}: exists and is not a directory; simulate writes a directory")
    if quiet:
        summary = simulate(preset, seed, out, drives, motion_distortion, max_scans, changes=changes,
                           changes_from_drive=changes_from_drive)
    else:
        from rich.progress import Progress

        with Progress(transient=False) as bar:
            tasks: dict[str, int] = {}

            def progress(name: str, i: int, n: int) -> None:
                if name not in tasks:
                    tasks[name] = bar.add_task(f"{name} scans", total=n)
                bar.update(tasks[name], completed=i)

            summary = simulate(preset, seed, out, drives, motion_distortion, max_scans, progress, changes=changes,
                               changes_from_drive=changes_from_drive)
    for name in summary.drives:
        st = summary.gnss_stats[name]
        typer.echo(f"{name}: {summary.n_scans[name]} scans, GNSS horizontal RMS {st['rms_m']:.2f} m, "
                   f"max {st['max_m']:.2f} m -> {out / name / 'drive.yaml'}")
