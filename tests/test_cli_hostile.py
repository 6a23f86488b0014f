"""Issue 22 finding 8: every CLI command, given missing, wrong or hostile arguments, ends with ONE line on
stderr ("error: ...") and exit code 1 (3 for data quality), never a traceback or an "internal error"."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.versioned import read_manifest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    from stages.tiles.compute import compute
    from tests.stages.tiles.tiles_synth import building_corners, buildings, city_context, corner_table

    root = tmp_path_factory.mktemp("hostile")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=3)))
    (root / "a_file").write_text("x")
    (root / "latin1.yaml").write_bytes("name: caf\u00e9\nstages: [ingest]\n".encode("latin-1"))
    (root / "dup.yaml").write_text("name: a\nname: b\nstages: [ingest]\n")
    (root / "bomb.yaml").write_text("a: &a [1, 1]\nb: &b [*a, *a]\nc: [*b, *b]\n")
    (root / "empty_map" / "maps" / "none").mkdir(parents=True)
    bad = root / "bad_manifest"
    (bad / "maps" / "city").mkdir(parents=True)
    (bad / "maps" / "city" / "v0001").mkdir()
    (bad / "maps" / "city" / "v0001" / "manifest.json").write_text("{not json")
    (bad / "maps" / "city" / "LATEST").write_text("v0001\n")
    latest_dir = root / "latest_dir"
    (latest_dir / "maps" / "city" / "LATEST").mkdir(parents=True)
    return root


def _cases(r: Path) -> list[tuple[str, ...]]:
    m = str(r / "maps" / "city")
    R = str(r)
    return [
        # missing and wrong arguments
        ("run",),
        ("run", f"{R}/nope.yaml"),
        ("run", R),
        ("run", f"{R}/a_file"),
        ("run", "--bogus"),
        ("run", f"{R}/latin1.yaml"),
        ("run", f"{R}/dup.yaml"),
        ("run", f"{R}/bomb.yaml"),
        ("run", str(REPO / "workflows" / "tiny.yaml"), "--only", "nope", "--dry-run"),
        ("run", str(REPO / "workflows" / "tiny.yaml"), "--params", f"{R}/bomb.yaml", "--dry-run"),
        ("build",),
        ("build", "--drive", f"{R}/a_file", "--map", "../../evil", "--root", R),
        ("catalog", "ls", f"{R}/nope"),
        ("catalog", "validate", f"{R}/dup.yaml"),
        ("ingest", "run", "--workflow", f"{R}/nope.yaml"),
        ("ingest", "describe", "extra"),
        ("corners", "params", "-x"),
        ("inspect",),
        ("inspect", f"{R}/nope.pcd"),
        ("inspect", f"{R}/a_file", "--format", "pcd"),
        ("inspect", f"{R}/a_file", "--sensor", "bogus"),
        ("inspect", f"{R}/a_file", "--format", "bogus"),
        ("simulate",),
        ("simulate", "--out", f"{R}/a_file", "--quiet"),
        ("simulate", "--out", f"{R}/sim", "--preset", "bogus", "--quiet"),
        ("evaluate",),
        ("evaluate", "--map", m, "--drive", f"{R}/nope.yaml", "--out", f"{R}/ev"),
        ("evaluate", "--map", m, "--drive", f"{R}/a_file", "--out", f"{R}/a_file"),
        # tiles: wrong names, hostile paths and options, broken maps
        ("tiles", "ls", "--root", f"{R}/nope"),
        ("tiles", "ls", "--root", R, "--map", "../.."),
        ("tiles", "diff", "v1", "v7", "--root", R),
        ("tiles", "diff", "v1", "v1", "--match-radius-m", "nan", "--root", R),
        ("tiles", "diff", "v1", "banana", "--root", R),
        ("tiles", "export", "--root", R),
        ("tiles", "export", "-f", "shp", "-o", f"{R}/x", "--root", R),
        ("tiles", "export", "-f", "geojson", "-o", f"{m}/LATEST", "--root", R),
        ("tiles", "export", "-f", "geojson", "-o", f"{m}/v0001/manifest.json", "--root", R),
        ("tiles", "export", "-f", "geojson", "-o", R, "--root", R),
        ("tiles", "export", "-f", "geojson", "-o", f"{R}/a_file/x.json", "--root", R),
        ("tiles", "export", "-f", "geotiff", "-o", f"{R}/a_file", "--root", R),
        ("tiles", "export", "-f", "markings-geojson", "-o", R, "--root", R),
        ("tiles", "export", "-f", "autoware", "-o", f"{R}/a_file", "--root", R),
        ("tiles", "verify", "--root", f"{R}/empty_map", "--all"),
        ("tiles", "export", "-f", "geojson", "-o", f"{R}/g.json", "--root", f"{R}/bad_manifest"),
        ("tiles", "diff", "v1", "v1", "--root", f"{R}/bad_manifest"),
        ("tiles", "ls", "--root", f"{R}/latest_dir"),
        ("tiles", "verify", "--root", f"{R}/latest_dir"),
        ("tiles", "export", "-f", "geojson", "-o", f"{R}/g.json", "--root", f"{R}/latest_dir"),
        ("drive", "init", f"{R}/nope"),
        ("drive", "init", f"{R}/a_file"),
        ("drive", "check"),
        ("drive", "check", f"{R}/nope.yaml"),
        ("drive", "check", f"{R}/bomb.yaml"),
        ("drive", "check", f"{R}/a_file"),
        ("drive", "check", f"{R}/dup.yaml"),
        ("build", "--drive", f"{R}/a_file", "--map", "city", "--root", R, "--origin", "north,1,2"),
        ("build", "--drive", f"{R}/a_file", "--map", "city", "--root", R, "--origin", "137.5,1,2"),
        ("run", "tinny", "--dry-run"),
        ("catalog", "validate", "--workflow", "nope"),
        ("bogus",),
        ("--bogus",),
    ]


def test_every_command_fails_with_one_line_and_exit_1(env, capsys):
    failures = []
    for args in _cases(env):
        with pytest.raises(SystemExit) as info:
            main(list(args))
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        ok = (info.value.code in (1, 3) and len(err) == 1 and err[0].startswith("error: ")
              and "internal error" not in err[0] and "Traceback" not in captured.err + captured.out)
        if not ok:
            failures.append((args, info.value.code, captured.err[-400:]))
    assert not failures, "\n".join(map(str, failures))


def test_hostile_commands_left_nothing_behind(env):
    test_leftovers = [p for p in env.rglob("*") if ".tmp-" in p.name]
    assert test_leftovers == []
    assert not (env / "sim").exists() or not any((env / "sim").iterdir())
    manifest, _ = read_manifest(env / "maps" / "city" / "v0001")
    assert json.loads((env / "maps" / "city" / "v0001" / "manifest.json").read_text()) == manifest


def test_verify_a_good_map_exits_0(env, capsys):
    main(["tiles", "verify", "--all", "--root", str(env)])  # returns normally: exit 0
    assert "v0001: ok" in capsys.readouterr().out
