"""How much of the docs is dated measurement history: lines in dated measurement sections per page and in total.

A *section* is a markdown heading and every line up to the next heading of any level (headings inside code
fences do not count; the lines before a page's first heading are a section of their own). A section is a *dated
measurement section* when its heading or body carries any of:

- a date, ``YYYY-MM-DD`` (2000-2099);
- a commit hash: a word of 7 to 40 lowercase hex characters with at least one digit and one letter, or a hash
  range ``abc1234..def5678`` / ``abc1234+`` ("measured at 4c6dbe1", "at 4c6dbe1+");
- a before/after figure: a number, an arrow and a number (``137.8 -> 125.2 s``, ``965 → 1058 MB``), or a word
  ``before``/``was``/``previously`` followed on the same line by a number and then ``now``/``after``.

A reference page states its *current* figure once, with the command that reproduces it and the machine, and
leaves the history to CHANGELOG.md and git: its sections carry none of these. The one date it may keep is a
figure's provenance: the cells of a table column headed ``last measured`` are not searched for dates (a hash or an
arrow there still counts). ``share`` is dated lines / lines.

    python -m bench.docs_history                      # docs/*.md, per page and total (the issue's measure)
    python -m bench.docs_history docs/performance.md  # some pages
    python -m bench.docs_history --json               # one JSON document
    python -m bench.docs_history --sections docs/posegraph.md   # which sections count, and why

Pure standard library; reads the pages only.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HEADING = re.compile(r"^#{1,6}\s")
FENCE = re.compile(r"^\s*(```|~~~)")
MARKERS = {
    "date": re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b"),
    "commit": re.compile(r"(?<![0-9a-zA-Z_/.-])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![0-9a-zA-Z_-])"),
    "before/after": re.compile(
        r"\d(?:[.,]\d+)?\s*(?:%|[a-zA-Z]{0,4})\s*(?:->|→)\s*-?\d"
        r"|\b(?:before|was|previously)\b[^.;]*\d[^.;]*\b(?:now|after)\b",
        re.IGNORECASE,
    ),
}


@dataclass(frozen=True)
class Section:
    heading: str
    first_line: int  # 1-based
    lines: int
    markers: tuple[str, ...]  # the kinds of marker found, empty when the section is not dated

    @property
    def dated(self) -> bool:
        return bool(self.markers)


@dataclass(frozen=True)
class PageShare:
    page: str
    lines: int
    dated_lines: int

    @property
    def share(self) -> float:
        return self.dated_lines / self.lines if self.lines else 0.0


def _cells(line: str) -> list[str]:
    return re.split(r"(?<!\\)\|", line.strip().strip("|"))


def _without_last_measured(lines: list[str]) -> list[str]:
    """The lines with the cells of every ``last measured`` table column blanked of dates."""
    out, col = [], None
    for n, line in enumerate(lines):
        if not line.lstrip().startswith("|"):
            col = None
        elif col is None and n + 1 < len(lines) and re.match(r"^\s*\|\s*:?-{3}", lines[n + 1]):
            header = [c.strip().lower() for c in _cells(line)]
            col = header.index("last measured") if "last measured" in header else -1
        elif col is not None and col >= 0:
            cells = _cells(line)
            if col < len(cells):
                cells[col] = MARKERS["date"].sub("", cells[col])
                line = "|" + "|".join(cells) + "|"
        out.append(line)
    return out


def sections(text: str) -> list[Section]:
    """The page's sections in order, each with the kinds of dated-measurement marker it carries."""
    lines = text.splitlines()
    searched = _without_last_measured(lines)
    starts, in_fence = [0], False
    for n, line in enumerate(lines):
        if FENCE.match(line):
            in_fence = not in_fence
        elif not in_fence and HEADING.match(line) and n > 0:
            starts.append(n)
    out = []
    for a, b in zip(starts, [*starts[1:], len(lines)]):
        if b <= a:
            continue
        body = "\n".join(searched[a:b])
        found = tuple(kind for kind, rx in MARKERS.items() if rx.search(body))
        heading = lines[a] if HEADING.match(lines[a]) else "(before the first heading)"
        out.append(Section(heading.strip(), a + 1, b - a, found))
    return out


def page_share(path: Path) -> PageShare:
    text = path.read_text(encoding="utf-8")
    secs = sections(text)
    try:
        name = str(path.resolve().relative_to(REPO))
    except ValueError:
        name = str(path)
    return PageShare(name, len(text.splitlines()), sum(s.lines for s in secs if s.dated))


def default_pages() -> list[Path]:
    return sorted((REPO / "docs").glob("*.md"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.docs_history", description=__doc__.split("\n\n")[0])
    ap.add_argument("pages", nargs="*", type=Path, help="markdown pages (default: docs/*.md)")
    ap.add_argument("--json", action="store_true", help="one JSON document on stdout")
    ap.add_argument("--sections", action="store_true", help="list each dated section with its markers")
    args = ap.parse_args(argv)
    pages = args.pages or default_pages()
    missing = [str(p) for p in pages if not p.is_file()]
    if missing:
        print(f"docs_history: no such page: {', '.join(missing)}", file=sys.stderr)
        return 1
    shares = [page_share(p) for p in pages]
    total = PageShare("total", sum(s.lines for s in shares), sum(s.dated_lines for s in shares))
    if args.json:
        rows = [{**asdict(s), "share": round(s.share, 4)} for s in [*shares, total]]
        if args.sections:
            for row, p in zip(rows, pages):
                row["dated_sections"] = [
                    {"heading": s.heading, "line": s.first_line, "lines": s.lines, "markers": list(s.markers)}
                    for s in sections(p.read_text(encoding="utf-8"))
                    if s.dated
                ]
        print(json.dumps({"pages": rows[:-1], "total": rows[-1]}, indent=1))
        return 0
    width = max(len(s.page) for s in [*shares, total])
    print(f"{'page':<{width}}  {'lines':>6}  {'dated':>6}  share")
    for s in [*shares, total]:
        print(f"{s.page:<{width}}  {s.lines:>6}  {s.dated_lines:>6}  {100 * s.share:5.1f} %")
        if args.sections and s is not total:
            for sec in sections((REPO / s.page if not Path(s.page).is_absolute() else Path(s.page)).read_text()):
                if sec.dated:
                    print(f"    {sec.first_line:>5} {sec.lines:>4} lines  {','.join(sec.markers):<24} {sec.heading}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
