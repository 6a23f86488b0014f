"""CSV columns by name -> float64 arrays, with non-numeric cells reported by record (0-based data row; file line
= record + 2 with one header line) instead of failing the file, when the caller takes them row by row."""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError


@dataclass(frozen=True)
class TimestampIssue:
    record: int
    reason: str


def read_header(path: Path, delimiter: str = ",") -> list[str]:
    """The header line's column names; a file that is not UTF-8 text is a FormatError naming it. A KITTI OXTS
    folder (``stages.ingest.kitti_raw``) is read like a CSV: its header is ``time`` and the 30 OXTS fields."""
    if Path(path).is_dir():
        from stages.ingest.kitti_raw import oxts_header

        return oxts_header(Path(path))
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            return [c.strip() for c in next(csv.reader(fh, delimiter=delimiter), [])]
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: header line is not UTF-8 text (byte {exc.start}: {exc.reason}); expected a "
                          f"CSV with a header line") from None
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read CSV: {exc.strerror or exc}") from exc


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
    try:
        table = pacsv.read_csv(
            path, read_options=pacsv.ReadOptions(use_threads=False),
            parse_options=pacsv.ParseOptions(delimiter=delimiter, invalid_row_handler=on_invalid),
            convert_options=pacsv.ConvertOptions(include_columns=wanted, column_types={n: pa.string() for n in wanted},
                                                 strings_can_be_null=True))
    except pa.ArrowInvalid as exc:
        raise FormatError(f"{path}: unreadable CSV: {exc}") from exc
    if bad:
        raise FormatError(f"{path}: {len(bad)} row(s) with the wrong number of columns: " + "; ".join(bad[:10]))
    return {n: _floats(table[n], path, n, bad_cells) for n in wanted}


def _floats(column, path: Path, name: str, bad_cells: list[TimestampIssue] | None) -> np.ndarray:
    """A string column -> float64; empty cells are NaN; non-numeric cells raise or are reported (see above)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    try:
        return pc.cast(column, pa.float64()).to_numpy(zero_copy_only=False).astype(np.float64)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        pass
    values = column.to_pylist()
    out = np.full(len(values), np.nan)
    for i, v in enumerate(values):
        if v is None or not v.strip():
            continue
        try:
            out[i] = float(v)
        except ValueError:
            if bad_cells is None:
                raise FormatError(f"{path}: record {i} (line {i + 2}), column {name!r}: {v[:40]!r} is not a "
                                  f"number") from None
            bad_cells.append(TimestampIssue(i, f"column {name!r}: {v[:40]!r} is not a number"))
    return out
