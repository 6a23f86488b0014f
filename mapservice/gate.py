"""The regression gate of ``cornermap rebuild``: is candidate version N+1 no worse than LATEST?

The check drive is localized on both versions by ``cornermap evaluate`` (corner EKF and marking MCL, reference
the drive's own pose graph unless the map names a truth trajectory) in one work folder, so the drive is ingested
once. Compared figures (metres, lower is better): ``GATE_FIGURES``. The candidate is refused when it has no
coverage of the check drive, or when a figure grows beyond ``max(tol_m, tol_rel * previous)``. A previous
version without coverage of the drive (new streets) has nothing to compare: the candidate passes. The table and
both metrics documents are written to ``maps/NAME/gate/vNNNN.json``.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from pipeline import storage

GATE_FIGURES = (("ekf", "rms_2d_m"), ("ekf", "p95_2d_m"), ("mcl", "rms_2d_m"), ("mcl", "p95_2d_m"))


@dataclass
class GateVerdict:
    ok: bool
    table: list[str] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)


def compare(candidate: dict | None, previous: dict | None, tol_m: float, tol_rel: float) -> GateVerdict:
    """Compare two evaluate metrics documents (None: the version had no coverage of the drive)."""
    if candidate is None:
        return GateVerdict(False, ["gate: the candidate has no map coverage of the check drive (evaluate exit 3)"])
    if previous is None:
        return GateVerdict(True, ["gate: the previous version has no coverage of the check drive; nothing to "
                                  "compare (passed)"])
    rows, ok = [], True
    table = [f"gate: {'figure':16s} {'previous':>10s} {'candidate':>10s} {'allowed':>10s}  verdict"]
    for method, key in GATE_FIGURES:
        a = previous.get("methods", {}).get(method, {}).get(key)
        b = candidate.get("methods", {}).get(method, {}).get(key)
        if a is None and b is None:
            continue
        if b is None:
            verdict, allowed = "worse (missing)", None
        elif a is None:
            verdict, allowed = "new", None
        else:
            allowed = a + max(tol_m, tol_rel * a)
            verdict = "ok" if b <= allowed else "worse"
        ok &= not verdict.startswith("worse")
        rows.append({"figure": f"{method}.{key}", "previous": a, "candidate": b, "allowed": allowed,
                     "verdict": verdict})
        fmt = lambda v: f"{v:10.4f}" if v is not None else f"{'-':>10s}"  # noqa: E731
        table.append(f"gate: {method + '.' + key:16s} {fmt(a)} {fmt(b)} {fmt(allowed)}  {verdict}")
    return GateVerdict(ok, table, rows)


def _evaluate(mdir: Path, version: int, drive: Path, reference: str | None, out: Path) -> dict | None:
    from mapservice.child import run_cornermap
    from pipeline.errors import StageError
    from pipeline.versioned import version_name

    res = run_cornermap(["evaluate", "--root", str(mdir.parent.parent), "--map", mdir.name, "--map-version",
                         version_name(version), "--drive", str(drive), "--reference", reference or "map", "--out",
                         str(out)], label="gate", step=f"{drive.parent.name} on {version_name(version)}")
    metrics = out / "metrics.json"
    if res.returncode not in (0, 3) or not metrics.is_file():
        raise StageError(f"gate: cornermap evaluate of {drive} on {version_name(version)} failed (exit "
                         f"{res.returncode}): {' '.join(res.stderr.split())[:500]}")
    doc = json.loads(metrics.read_text())
    metrics.unlink()
    coverage = doc.get("verdict", {}).get("coverage", {})
    return doc if coverage.get("ok", True) else None


def run_gate(mdir: Path, candidate: int, previous: int, drive: Path, reference: str | None,
             tol_m: float, tol_rel: float) -> GateVerdict:
    from pipeline.progress import finish, report
    from pipeline.store import atomic_write_json
    from pipeline.versioned import version_name

    gate_dir = storage.gate_dir(mdir)
    work = gate_dir / f".work-{version_name(candidate)}"
    try:
        report("gate", 0, 2)
        cand = _evaluate(mdir, candidate, drive, reference, work)
        report("gate", 1, 2)
        prev = _evaluate(mdir, previous, drive, reference, work)
        report("gate", 2, 2)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    verdict = compare(cand, prev, tol_m, tol_rel)
    finish("gate", "passed" if verdict.ok else "refused")
    atomic_write_json(storage.gate_file(mdir, candidate), {
        "candidate": candidate, "previous": previous, "check_drive": str(drive), "reference": reference or "map",
        "tol_m": tol_m, "tol_rel": tol_rel, "ok": verdict.ok, "rows": verdict.rows,
        "candidate_metrics": cand and cand.get("methods"), "previous_metrics": prev and prev.get("methods")})
    return verdict
