"""Only the store spells the store's layout (issue 58): no production module outside ``pipeline/storage.py`` builds a
path from a layout name (``datasets``, ``maps``, ``LATEST``, ``_manifest.json``, ...); they ask the store's layout
functions. What remains is allow-listed here with its reason. Tests and benchmarks may spell the layout: they are
the independent oracle of the on-disk format."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "mapservice", "mapformat", "stages", "schemas")
STORE = {"pipeline/storage.py"}
NAMES = r"(datasets|maps|locks|tmp|gate|artifacts|_parts|LATEST|manifest\.json|_manifest\.json|map\.json|workflows)"
PATTERNS = {
    "a path joined with a layout name": re.compile(rf"""/\s*["']{NAMES}["']|["']{NAMES}["']\s*/(?!/)"""),
    "a layout name handed to inside()/joinpath()": re.compile(rf"""(inside|joinpath)\([^)\n]*["']{NAMES}["']"""),
    "a store-only file name": re.compile(r"""["'](_manifest\.json|_parts|map\.json|\.publish\.lock)["']"""),
    "a layout path in an f-string": re.compile(r"""f["']([^"'\n]*\}/)?(datasets|maps|_parts|artifacts|LATEST)/"""),
}
# file -> (pattern name, why it stays)
ALLOWED = {
    ("pipeline/testing.py", "a path joined with a layout name"):
        "a stage test harness's own work folder (WORKDIR/artifacts/KEY), not an output root",
}


def spelled() -> list[tuple[str, int, str, str]]:
    out = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            if rel in STORE:
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                code = line.split("#", 1)[0]
                for what, pat in PATTERNS.items():
                    if pat.search(code) and (rel, what) not in ALLOWED:
                        out.append((rel, n, what, line.strip()))
    return out


def test_no_module_outside_the_store_spells_the_layout():
    found = spelled()
    assert not found, "the layout is spelled outside pipeline/storage.py (use its functions):\n" + "\n".join(
        f"  {rel}:{n}: {what}: {line}" for rel, n, what, line in found)


def test_every_allowance_is_still_needed():
    used = {(rel, what) for pkg in PACKAGES for path in sorted((REPO / pkg).rglob("*.py"))
            for rel in [path.relative_to(REPO).as_posix()] for line in path.read_text(encoding="utf-8").splitlines()
            for what, pat in PATTERNS.items() if pat.search(line.split("#", 1)[0])}
    assert set(ALLOWED) <= used, f"allowances no longer needed: {sorted(set(ALLOWED) - used)}"


def test_the_check_finds_a_spelled_layout():
    sample = ['d = root / "datasets" / ds', 'm = mdir / "LATEST"', 'inside(d, "artifacts", label)',
              'marker = "_manifest.json"', 'p = f"{root}/maps/{name}"']
    for line in sample:
        assert any(p.search(line) for p in PATTERNS.values()), line
    for line in ['out[v] = "LATEST"', 'version: str = "LATEST"', 'm.get("artifacts", {})', 'report("gate", 0, 2)']:
        assert not any(p.search(line) for p in PATTERNS.values()), line
