"""``cornermap simulate``: generate a synthetic city and drives (heavy imports inside the command)."""
from __future__ import annotations

from pathlib import Path

import typer

from pipeline import cli_options as opts


def register(app: typer.Typer) -> None:
    app.command("simulate", help=(
        "Generate a synthetic city and K drives (HDL-32E PCD scans, INSPVA GNSS/INS CSV, wheel/gyro CSV, "
        "survey LAS, ground truth), deterministic from (preset, seed).\n\n"
        "Examples:\n\n"
        "  cornermap simulate --preset tiny --seed 7 --out runs/sim\n\n"
        "  cornermap simulate --preset gangnam --seed 3 --out runs/gangnam_sim --drives 3 --max-scans 20\n\n"
        "  cornermap simulate --preset demo --out runs/demo_sim --no-motion-distortion --max-scans 50\n\n"
        "  cornermap simulate --preset demo --out runs/demo_lead --set queue_stop_share=0 "
        "--set lead_vehicle_share=0.7\n\n"
        "  (a vehicle ahead in >= 50% of the scans; lead_vehicle_share=0: the same city and drives without it)\n\n"
        "  cornermap simulate --preset tiny --seed 7 --drives 3 --changes --out runs/tiny_changed\n\n"
        "  cornermap simulate --preset tiny_consumer --seed 7 --out runs/consumer\n\n"
        "  (no survey, consumer GNSS, the lidar 0.95 m ahead and turned -90 deg, facade detail)\n\n"
        "  cornermap simulate --preset kitti_city --seed 7 --out runs/kitti_city\n\n"
        "  (the HDL-64E in a KITTI-like street)\n\n"
        "  cornermap simulate --preset tiny --out runs/tiny_nosurvey --set survey=0 --set lidar_yaw_deg=90"
    ))(simulate_command)


def simulate_command(
    preset: str = typer.Option("tiny", help="tiny | demo | gangnam | tiny_consumer | demo_consumer | kitti_city | "
                               "growing"),
    seed: int = typer.Option(0, help="random seed; same preset and seed give identical files"),
    out: Path = typer.Option(..., help="output directory (drive_K/, survey/, truth/)"),
    drives: int = typer.Option(None, help="number of drives (drive 0 maps, later ones evaluate); default 2"),
    motion_distortion: bool = typer.Option(True, help="roll each scan during motion (per-firing poses)"),
    max_scans: int = typer.Option(None, help="cap the scans written per drive (quick looks, tests)"),
    quiet: bool = opts.QUIET,
    set_: list[str] = typer.Option([], "--set", help="change a preset field, KEY=VALUE or KEY=LO,HI (repeatable), "
                                   "e.g. lead_vehicle_share=0.6, corner_radius_m=1,5; an unknown KEY lists the "
                                   "preset's fields"),
    changes: bool = typer.Option(False, "--changes", help="the city changes before the last drive (a building "
                                 "demolished, one built, a crosswalk moved); truth in truth/changes.json"),
    changes_from_drive: int = typer.Option(None, help="with --changes: first drive that sees the changed city"),
) -> None:
    from pipeline.errors import DatasetIOError
    from stages.simulate.core import simulate

    if out.exists() and not out.is_dir():
        raise DatasetIOError(f"--out {out}: exists and is not a directory; simulate writes a directory")
    from pipeline.errors import ConfigError, OptionError
    from stages.simulate.presets import get_preset

    try:
        preset = get_preset(preset, **parse_overrides(set_))
    except ConfigError as exc:  # an unknown preset or field, a value out of range: the command line is wrong
        raise OptionError(exc.where.replace("simulate ", ""), exc.problems) from None
    from pipeline.progress import StageProgress

    with StageProgress(enabled=not quiet) as display:
        def progress(name: str, i: int, n: int) -> None:
            display.update(f"{name} scans", i, n)
            if i >= n:
                display.finish(f"{name} scans")

        summary = simulate(preset, seed, out, drives, motion_distortion, max_scans,
                           progress if display.enabled else None, changes=changes,
                           changes_from_drive=changes_from_drive)
    for name in summary.drives:
        st = summary.gnss_stats[name]
        what = f"GNSS horizontal RMS {st['rms_m']:.2f} m, max {st['max_m']:.2f} m" if preset.gnss else \
            f"no GNSS ({'start pose' if preset.prior == 'none' else f'{preset.prior} prior trajectory + start pose'})"
        typer.echo(f"{name}: {summary.n_scans[name]} scans, {what} -> {out / name / 'drive.yaml'}")


def parse_overrides(items: list[str]) -> dict:
    """``KEY=VALUE`` / ``KEY=LO,HI`` / ``KEY=NAME`` strings -> preset field overrides (floats, a pair of floats, or
    a name such as ``sensor=hdl64e``)."""
    from pipeline.errors import ConfigError

    out, bad = {}, []
    for item in items:
        key, sep, value = item.partition("=")
        try:
            nums = tuple(float(v) for v in value.split(","))
        except ValueError:
            nums = ()
        name = value.strip()
        if sep and key and not nums and name.replace("-", "_").isidentifier():  # a name: sensor=os1-64
            out[key.strip()] = name
            continue
        if not sep or not key or len(nums) not in (1, 2):
            bad.append(f"--set {item!r}: expected KEY=NUMBER, KEY=LO,HI or KEY=NAME")
            continue
        out[key.strip()] = nums[0] if len(nums) == 1 else nums
    if bad:
        raise ConfigError("simulate --set", bad)
    return out
