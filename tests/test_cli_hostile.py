"""Issue 22 finding 8: every CLI command, given missing, wrong or hostile arguments, ends with ONE line on
stderr ("error: ...") and its exit code: 2 when the command line itself is wrong (unknown command or option, a
missing or malformed option value), 1 when the work failed; never a traceback or an "internal error"."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapservice.cli import main
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


def _cases(r: Path) -> list[tuple[int, tuple[str, ...]]]:
    """(expected exit code, arguments): 2 where the command line itself is wrong, 1 where the work failed."""
    m = str(r / "maps" / "city")
    R = str(r)
    return [
        # missing and wrong arguments
        (2, ("run",)),
        (1, ("run", f"{R}/nope.yaml")),
        (1, ("run", R)),
        (1, ("run", f"{R}/a_file")),
        (2, ("run", "--bogus")),
        (1, ("run", f"{R}/latin1.yaml")),
        (1, ("run", f"{R}/dup.yaml")),
        (1, ("run", f"{R}/bomb.yaml")),
        (1, ("run", str(REPO / "workflows" / "tiny.yaml"), "--only", "nope", "--dry-run")),
        (1, ("run", str(REPO / "workflows" / "tiny.yaml"), "--params", f"{R}/bomb.yaml", "--dry-run")),
        (2, ("build",)),
        (2, ("build", "--drive", f"{R}/a_file", "--map", "../../evil", "--root", R)),
        (1, ("catalog", "ls", f"{R}/nope")),
        (1, ("catalog", "validate", f"{R}/dup.yaml")),
        (1, ("ingest", "run", "--workflow", f"{R}/nope.yaml")),
        (2, ("ingest", "describe", "extra")),
        (2, ("corners", "params", "-x")),
        (2, ("inspect",)),
        (1, ("inspect", f"{R}/nope.pcd")),
        (1, ("inspect", f"{R}/a_file", "--format", "pcd")),
        (2, ("inspect", f"{R}/a_file", "--sensor", "bogus")),
        (2, ("inspect", f"{R}/a_file", "--format", "bogus")),
        (2, ("simulate",)),
        (1, ("simulate", "--out", f"{R}/a_file", "--quiet")),
        (2, ("simulate", "--out", f"{R}/sim", "--preset", "bogus", "--quiet")),
        (2, ("evaluate",)),
        (1, ("evaluate", "--root", R, "--map", "city", "--drive", f"{R}/nope.yaml", "--out", f"{R}/ev")),
        (1, ("evaluate", "--root", R, "--map", "city", "--drive", f"{R}/a_file", "--out", f"{R}/a_file")),
        (2, ("evaluate", "--root", R, "--map", m, "--drive", f"{R}/a_file", "--out", f"{R}/ev")),  # a path, not a name
        (2, ("evaluate", "--root", R, "--map", "city", "--version", "v1", "--drive", f"{R}/a_file",
             "--out", f"{R}/ev")),
        (2, ("evaluate", "--root", R, "--map", "city", "--drive", f"{R}/a_file", "--out", f"{R}/ev",
             "--method", "kalman")),
        (2, ("evaluate", "--drive", f"{R}/a_file", "--out", f"{R}/ev")),  # no --root (nor CORNERMAP_ROOT)
        # tiles: wrong names, hostile paths and options, broken maps
        (1, ("tiles", "ls", "--root", f"{R}/nope")),
        (2, ("tiles", "ls", "--root", R, "--map", "../..")),
        (1, ("tiles", "diff", "v1", "v7", "--root", R)),
        (2, ("tiles", "diff", "v1", "v1", "--match-radius-m", "nan", "--root", R)),
        (1, ("tiles", "diff", "v1", "banana", "--root", R)),
        (2, ("tiles", "export", "--root", R)),
        (2, ("tiles", "export", "-f", "shp", "-o", f"{R}/x", "--root", R)),
        (1, ("tiles", "export", "-f", "geojson", "-o", f"{m}/LATEST", "--root", R)),
        (1, ("tiles", "export", "-f", "geojson", "-o", f"{m}/v0001/manifest.json", "--root", R)),
        (1, ("tiles", "export", "-f", "geojson", "-o", R, "--root", R)),
        (1, ("tiles", "export", "-f", "geojson", "-o", f"{R}/a_file/x.json", "--root", R)),
        (1, ("tiles", "export", "-f", "geotiff", "-o", f"{R}/a_file", "--root", R)),
        (1, ("tiles", "export", "-f", "markings-geojson", "-o", R, "--root", R)),
        (1, ("tiles", "export", "-f", "autoware", "-o", f"{R}/a_file", "--root", R)),
        (1, ("tiles", "export", "-f", "tum", "-o", f"{R}/empty_map", "--root", R)),  # non-empty, no --overwrite
        (1, ("tiles", "verify", "--root", f"{R}/empty_map", "--all")),
        (2, ("tiles", "export", "-f", "geojson", "-o", f"{R}/g.json", "--root", R, "--version", "v1")),  # --map-version
        (2, ("tiles", "verify", "--version", "v1", "--root", R)),
        (2, ("tiles", "ls")),  # no --root
        (2, ("maps", "create", "--root", R, "--map", "c", "--origin", "1,2,3", "--tile-size-m", "0")),
        (2, ("rebuild", "--root", R, "--map", "c", "--inbox", R, "--gate-tol-m", "-1")),
        (1, ("tiles", "export", "-f", "geojson", "-o", f"{R}/g.json", "--root", f"{R}/bad_manifest")),
        (1, ("tiles", "diff", "v1", "v1", "--root", f"{R}/bad_manifest")),
        (1, ("tiles", "ls", "--root", f"{R}/latest_dir")),
        (1, ("tiles", "verify", "--root", f"{R}/latest_dir")),
        (1, ("tiles", "export", "-f", "geojson", "-o", f"{R}/g.json", "--root", f"{R}/latest_dir")),
        (1, ("drive", "init", f"{R}/nope")),
        (1, ("drive", "init", f"{R}/a_file")),
        (2, ("drive", "check")),
        (1, ("drive", "check", f"{R}/nope.yaml")),
        (1, ("drive", "check", f"{R}/bomb.yaml")),
        (1, ("drive", "check", f"{R}/a_file")),
        (1, ("drive", "check", f"{R}/dup.yaml")),
        (2, ("build", "--drive", f"{R}/a_file", "--map", "city", "--root", R, "--origin", "north,1,2")),
        (2, ("build", "--drive", f"{R}/a_file", "--map", "city", "--root", R, "--origin", "137.5,1,2")),
        (1, ("run", "tinny", "--dry-run")),
        (1, ("catalog", "validate", "--workflow", "nope")),
        (2, ("bogus",)),
        (2, ("--bogus",)),
    ]


def test_every_command_fails_with_one_line_and_its_exit_code(env, capsys):
    failures = []
    for code, args in _cases(env):
        with pytest.raises(SystemExit) as info:
            main(list(args))
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        ok = (info.value.code == code and len(err) == 1 and err[0].startswith("error: ")
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
