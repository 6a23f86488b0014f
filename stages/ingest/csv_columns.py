"""CSV columns by name -> float64 arrays, with non-numeric cells reported by record (0-based data row; file line
= record + 2 with one header line) instead of failing the file, when the caller takes them row by row."""
from __future__ import annotations

import contextlib
import csv
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError


@dataclass(frozen=True)
class TimestampIssue:
    record: int
    reason: str


MAX_HEADER_BYTES = 1 << 16


def read_header(path: Path, delimiter: str = ",") -> list[str]:
    """The header line's column names; a header that is not UTF-8 text is a FormatError naming the file. Only the
    header line is decoded (a bad byte further down is the business of the column that holds it). A KITTI OXTS
    folder (``stages.ingest.kitti_raw``) is read like a CSV: its header is ``time`` and the 30 OXTS fields."""
    if Path(path).is_dir():
        from stages.ingest.kitti_raw import oxts_header

        return oxts_header(Path(path))
    try:
        with open(path, "rb") as fh:
            raw = fh.readline(MAX_HEADER_BYTES)
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read CSV: {exc.strerror or exc}") from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: line 1 (the header) is not UTF-8 text (byte {exc.start}: {exc.reason}); "
                          "expected a CSV with a header line") from None
    return [c.strip() for c in next(csv.reader([text], delimiter=delimiter), [])]


def read_csv_columns(
    path: Path, names: list[str], delimiter: str = ",", *, bad_cells: list[TimestampIssue] | None = None
) -> dict[str, np.ndarray]:
    """Named columns as float64. Rows with the wrong number of values raise FormatError listing them (up to 10)
    with their record numbers. A non-numeric cell raises too, unless ``bad_cells`` is given: then the cell
    becomes NaN and a (record, reason) is appended, so that the caller rejects that row only."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    if Path(path).is_dir():  # a KITTI OXTS folder: every value a number, or a FormatError naming the file
        from stages.ingest.kitti_raw import read_oxts_columns

        return read_oxts_columns(Path(path), list(dict.fromkeys(names)))
    header = read_header(path, delimiter)
    missing = [n for n in dict.fromkeys(names) if n not in header]
    if missing:
        raise FormatError(f"{path}: CSV lacks column(s) {', '.join(missing)}; header has {', '.join(header)}. "
                          f"Hint: fix the column mapping in drive.yaml")
    bad: list[str] = []

    def on_invalid(row) -> str:
        line = f"line {row.number}" if row.number is not None else "a row"
        bad.append(f"{line}: {row.actual_columns} values, expected {row.expected_columns}")
        return "skip"

    wanted = list(dict.fromkeys(names))
    with _undecodable_rows_stay_quiet():  # pyarrow decodes a bad row's text for the handler; see below
        try:
            table = pacsv.read_csv(
                path, read_options=pacsv.ReadOptions(use_threads=False),
                parse_options=pacsv.ParseOptions(delimiter=delimiter, invalid_row_handler=on_invalid),
                convert_options=pacsv.ConvertOptions(include_columns=wanted,
                                                     column_types={n: pa.binary() for n in wanted},
                                                     strings_can_be_null=True))
        except pa.ArrowInvalid as exc:
            raise FormatError(f"{path}: unreadable CSV: {exc}") from exc
    if bad:
        raise FormatError(f"{path}: {len(bad)} row(s) with the wrong number of columns: " + "; ".join(bad[:10]))
    return {n: _floats(table[n], path, n, bad_cells) for n in wanted}


@contextlib.contextmanager
def _undecodable_rows_stay_quiet():
    """pyarrow decodes a row with the wrong number of values as UTF-8 before calling the invalid-row handler; when it
    is not UTF-8 the decoding error is "ignored" (printed to stderr as a traceback) and the row ends the read as a
    parse error (a FormatError here). Within this block that print is not made: one line reaches the user."""
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if not isinstance(unraisable.exc_value, UnicodeDecodeError):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _floats(column, path: Path, name: str, bad_cells: list[TimestampIssue] | None) -> np.ndarray:
    """A bytes column -> float64; empty cells are NaN; cells that are not UTF-8 text or not a number raise or are
    reported (see above). Only the columns asked for are decoded."""
    import pyarrow as pa
    import pyarrow.compute as pc

    try:
        return pc.cast(pc.cast(column, pa.string()), pa.float64()).to_numpy(zero_copy_only=False).astype(np.float64)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        pass
    values = column.to_pylist()
    out = np.full(len(values), np.nan)
    for i, raw in enumerate(values):
        if raw is None or not raw.strip():
            continue
        try:
            out[i] = float(raw.decode("utf-8"))
            continue
        except UnicodeDecodeError:
            why = "is not UTF-8 text"
        except ValueError:
            why = f"{raw.decode('utf-8')[:40]!r} is not a number"
        if bad_cells is None:
            raise FormatError(f"{path}: record {i} (line {i + 2}), column {name!r}: {why}") from None
        bad_cells.append(TimestampIssue(i, f"line {i + 2}, column {name!r}: {why}"))
    return out
