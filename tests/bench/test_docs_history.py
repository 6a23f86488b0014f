"""bench/docs_history.py: which sections count as dated measurement history, on pages with known answers."""

from __future__ import annotations

import json

from bench.docs_history import main, page_share, sections

PAGE = """# Title
What the stage does.

## Measured
Demo build 137.8 -> 125.2 s.

## Method
```bash
# a comment in a code block is no heading 2026-01-01
```
The fingerprint holds no location.

## Figures
| what | figure | last measured |
|---|---|---|
| build | 110.0 s | 2026-11-30 |

## Provenance
| what | last measured |
|---|---|
| build | at 4c6dbe1 |

### Old run
measured 2026-11-24 on AMD EPYC
"""


def test_each_marker_kind_and_the_section_bounds():
    secs = {s.heading: s for s in sections(PAGE)}
    assert secs["## Measured"].markers == ("before/after",) and secs["## Measured"].lines == 3
    # the fenced "# ..." line neither starts a section nor escapes the date check: the whole fenced block is Method's
    assert secs["## Method"].lines == 6 and secs["## Method"].markers == ("date",)
    assert secs["## Figures"].markers == ()  # a date in a "last measured" column is a figure's provenance
    assert secs["## Provenance"].markers == ("commit",)  # a hash there is not
    assert secs["### Old run"].markers == ("date",)
    assert secs["# Title"].markers == ()
    assert sum(s.lines for s in secs.values()) == len(PAGE.splitlines())


def test_words_numbers_and_arrows_that_are_not_history():
    text = (
        "# A\nraw drive -> ingest -> pose graph; v0001 -> v0002; sha256 of 64 hex below\n"
        + "a" * 7
        + "\n"
        + "0123456789abcdef" * 4
        + "\n"
    )
    assert [s.markers for s in sections(text)] == [()]


def test_page_share_and_json(tmp_path, capsys):
    page = tmp_path / "p.md"
    page.write_text(PAGE)
    share = page_share(page)
    assert share.lines == 24 and share.dated_lines == 3 + 6 + 5 + 2  # Measured, Method, Provenance, Old run
    assert main([str(page), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["total"]["dated_lines"] == share.dated_lines and doc["pages"][0]["lines"] == 24
    assert main([str(tmp_path / "missing.md")]) == 1
