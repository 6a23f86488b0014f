"""PCD v0.7 reader (ascii, binary, binary_compressed) keeping every field, plus a small writer.

Why not open3d: ``open3d.t.io.read_point_cloud`` keeps extra fields, but on a truncated or corrupt file it
logs a warning and returns an empty cloud (no reason, no offset), and it offers no view of trailing padding.
This reader is strict about the header, reads exactly ``POINTS`` records (trailing padding is tolerated and
measured), and raises ``FormatError`` naming the file, the byte offset or record and expected vs got.
Tests cross-check it against open3d on files open3d writes (including binary_compressed).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError
from stages.ingest.lzf import LzfError, compress_literal_lzf, decompress_lzf

MAX_HEADER_BYTES = 65536
MAX_RECORD_BYTES = 4096  # one point's record; real scans use 16-48 bytes
MAX_POINTS = 20_000_000  # per scan; a 128-beam sensor gives ~2.6 M points per sweep
MAX_DECOMPRESSED_BYTES = 512 << 20  # binary_compressed output cap ...
MAX_COMPRESSION_RATIO = 64  # ... and ratio cap (real scans compress 1.2-4x; LZF's own maximum is ~88x)
_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
_ENCODINGS = ("ascii", "binary", "binary_compressed")


@dataclass(frozen=True)
class PcdHeader:
    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    width: int
    height: int
    points: int
    encoding: str
    data_offset: int  # byte offset of the first data byte
    viewpoint: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    @property
    def record_size(self) -> int:
        return sum(s * c for s, c in zip(self.sizes, self.counts))

    def dtype(self) -> np.dtype:
        """Packed little-endian record dtype; PCL's '_' padding fields get unique names."""
        names = [_pad_name(i) if name == "_" else name for i, name in enumerate(self.fields)]
        formats = [(("<" + _TYPES[(t, s)]), (c,)) if c > 1 else "<" + _TYPES[(t, s)]
                   for t, s, c in zip(self.types, self.sizes, self.counts)]
        return np.dtype({"names": names, "formats": formats})


def _pad_name(i: int) -> str:
    """A name for PCL's i-th '_' padding field that no FIELDS entry can take (FIELDS are split on spaces)."""
    return f"pad {i}"


@dataclass(frozen=True)
class PcdCloud:
    header: PcdHeader
    columns: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) or (N, COUNT); padding fields dropped
    trailing_bytes: int = 0  # bytes after the last record (zero padding in KITTI exports)


def _fail(source: str, what: str, hint: str = "") -> FormatError:
    return FormatError(f"{source}: {what}" + (f". Hint: {hint}" if hint else ""))


def _ints(source: str, key: str, values: list[str], minimum: int) -> list[int]:
    try:
        out = [int(v) for v in values]
    except ValueError:
        raise _fail(source, f"header {key} expects integers, got {' '.join(values)!r}") from None
    if any(v < minimum for v in out):
        raise _fail(source, f"header {key} expects integers >= {minimum}, got {' '.join(values)!r}")
    return out


def parse_pcd_header(buf: bytes, source: str = "<pcd>") -> PcdHeader:
    """Parse the text header up to and including the DATA line."""
    entries: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = buf.find(b"\n", pos, MAX_HEADER_BYTES)
        if end < 0:
            raise _fail(source, f"no DATA line in the first {min(len(buf), MAX_HEADER_BYTES)} bytes",
                        "this is not a PCD v0.7 file, or it was cut inside the header")
        try:
            line = buf[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise _fail(source, f"non-ASCII bytes in the header line at byte offset {pos}",
                        "garbage bytes before the DATA line") from None
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key not in ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS",
                       "DATA"):
            raise _fail(source, f"unknown header keyword {key!r} at byte offset {pos - len(line) - 1}")
        if key in entries:
            raise _fail(source, f"header keyword {key} appears twice")
        entries[key] = values
        if key == "DATA":
            break
    return _build_header(entries, pos, source)


def _build_header(entries: dict[str, list[str]], data_offset: int, source: str) -> PcdHeader:
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA") if k not in entries]
    if missing:
        raise _fail(source, f"header lacks {', '.join(missing)}")
    version = entries.get("VERSION", ["0.7"])
    if version not in (["0.7"], [".7"]):
        raise _fail(source, f"unsupported PCD VERSION {' '.join(version)!r}, expected 0.7")
    fields = tuple(entries["FIELDS"])
    sizes = tuple(_ints(source, "SIZE", entries["SIZE"], 1))
    types = tuple(entries["TYPE"])
    counts = tuple(_ints(source, "COUNT", entries.get("COUNT", ["1"] * len(fields)), 1))
    lengths = {"FIELDS": len(fields), "SIZE": len(sizes), "TYPE": len(types), "COUNT": len(counts)}
    if not fields or len(set(lengths.values())) != 1:
        raise _fail(source, f"header lists disagree in length: {lengths}")
    for name, t, s in zip(fields, types, sizes):
        if (t, s) not in _TYPES:
            raise _fail(source, f"field {name!r} has TYPE {t} SIZE {s}; expected F 4/8, I or U 1/2/4/8")
    named = [f for f in fields if f != "_"]
    if len(set(named)) != len(named):
        raise _fail(source, f"duplicate field names in FIELDS {' '.join(fields)}")
    record = sum(s * c for s, c in zip(sizes, counts))
    if record > MAX_RECORD_BYTES:
        raise _fail(source, f"a record of {record} bytes (SIZE x COUNT summed), more than the {MAX_RECORD_BYTES}-byte "
                            "limit", "COUNT is corrupt")
    (width,), (height,) = _ints(source, "WIDTH", entries["WIDTH"][:1] or ["x"], 0), \
        _ints(source, "HEIGHT", entries["HEIGHT"][:1] or ["x"], 0)
    points = width * height
    if "POINTS" in entries:
        (points,) = _ints(source, "POINTS", entries["POINTS"][:1] or ["x"], 0)
        if points != width * height:
            raise _fail(source, f"header POINTS {points} != WIDTH {width} x HEIGHT {height}",
                        "the header counts lie; the file was edited or cut")
    if points > MAX_POINTS:
        raise _fail(source, f"POINTS {points}, more than the limit of {MAX_POINTS} per scan", "the header counts lie")
    encoding = entries["DATA"][0].lower() if entries["DATA"] else ""
    if encoding not in _ENCODINGS:
        raise _fail(source, f"DATA {' '.join(entries['DATA'])!r}, expected one of {', '.join(_ENCODINGS)}")
    try:
        viewpoint = tuple(float(v) for v in entries.get("VIEWPOINT", [])) or PcdHeader.viewpoint
    except ValueError:
        raise _fail(source, f"header VIEWPOINT expects 7 numbers, got {' '.join(entries['VIEWPOINT'])!r}") from None
    return PcdHeader(fields, sizes, types, counts, width, height, points, encoding, data_offset, viewpoint)


def _records_binary(buf: bytes, h: PcdHeader, source: str) -> tuple[np.ndarray, int]:
    need = h.points * h.record_size
    have = len(buf) - h.data_offset
    if have < need:
        raise _fail(source, f"truncated binary data: POINTS {h.points} x {h.record_size} bytes/record = {need} "
                            f"bytes from byte offset {h.data_offset}, file has {have} (record "
                            f"{have // h.record_size} is the first incomplete one)",
                    "the file was cut short; re-export it")
    _check_trailing(buf, h.data_offset + need, h, source)
    return np.frombuffer(buf, dtype=h.dtype(), count=h.points, offset=h.data_offset), have - need


def _check_trailing(buf: bytes, end: int, h: PcdHeader, source: str) -> None:
    """Zero padding after the last record is tolerated; a whole non-zero record more means POINTS lies."""
    extra = len(buf) - end
    if h.record_size and extra >= h.record_size and any(buf[end:]):
        raise _fail(source, f"{extra} bytes of non-zero data after the {h.points} records POINTS announces (at least "
                            f"{extra // h.record_size} more records)", "POINTS is smaller than the data")


def _records_compressed(buf: bytes, h: PcdHeader, source: str) -> tuple[np.ndarray, int]:
    at = h.data_offset
    if len(buf) < at + 8:
        raise _fail(source, f"binary_compressed data cut before its 8-byte size prefix at byte offset {at}")
    csize, usize = (int(v) for v in np.frombuffer(buf, "<u4", 2, at))
    need = h.points * h.record_size
    if usize > MAX_DECOMPRESSED_BYTES or usize > MAX_COMPRESSION_RATIO * max(csize, 1) + 64:
        raise _fail(source, f"binary_compressed announces {usize} bytes from {csize} compressed bytes; limits are "
                            f"{MAX_DECOMPRESSED_BYTES} bytes and a ratio of {MAX_COMPRESSION_RATIO}",
                    "a decompression bomb or a corrupt size prefix")
    if usize != need:
        raise _fail(source, f"binary_compressed announces {usize} uncompressed bytes, expected POINTS {h.points} "
                            f"x {h.record_size} bytes/record = {need}", "the header counts lie")
    if len(buf) < at + 8 + csize:
        raise _fail(source, f"truncated binary_compressed data: {csize} compressed bytes announced at byte "
                            f"offset {at + 8}, file has {len(buf) - at - 8}")
    try:
        raw = decompress_lzf(buf[at + 8:at + 8 + csize], usize) if need else b""
    except LzfError as exc:
        raise _fail(source, f"corrupt LZF stream after byte offset {at + 8}: {exc}") from exc
    records = np.empty(h.points, dtype=h.dtype())
    start = 0
    for name in records.dtype.names:  # column-major: all values of one field, then the next
        sub = records.dtype[name]
        nbytes = h.points * sub.itemsize
        records[name] = np.frombuffer(raw, sub.base, h.points * max(1, sub.itemsize // sub.base.itemsize),
                                      start).reshape(records[name].shape)
        start += nbytes
    _check_trailing(buf, at + 8 + csize, h, source)
    return records, len(buf) - at - 8 - csize


def _records_ascii(buf: bytes, h: PcdHeader, source: str) -> tuple[np.ndarray, int]:
    try:
        text = buf[h.data_offset:].decode("ascii")
    except UnicodeDecodeError as exc:
        raise _fail(source, f"non-ASCII byte in ascii data at byte offset {h.data_offset + exc.start}") from None
    lines = [ln for ln in text.splitlines() if ln.strip()]
    width = sum(h.counts)
    if len(lines) < h.points:
        raise _fail(source, f"truncated ascii data: header says POINTS {h.points}, file has {len(lines)} records")
    if len(lines) > h.points:
        raise _fail(source, f"ascii data has {len(lines)} records, header says POINTS {h.points}",
                    "POINTS is smaller than the data")
    body = lines[:h.points]
    n_tokens = np.fromiter((len(ln.split()) for ln in body), dtype=np.int64, count=h.points)
    bad = np.flatnonzero(n_tokens != width)
    if bad.size:
        raise _fail(source, f"ascii record {bad[0]} has {n_tokens[bad[0]]} values, expected {width} "
                            f"({bad.size} bad records)")
    try:
        values = np.array(" ".join(body).split(), dtype=np.float64).reshape(h.points, width)
    except ValueError:
        for i, ln in enumerate(body):
            try:
                np.array(ln.split(), dtype=np.float64)
            except ValueError:
                raise _fail(source, f"ascii record {i} is not numeric: {ln[:80]!r}") from None
        raise
    records = np.empty(h.points, dtype=h.dtype())
    col = 0
    for name, count in zip(records.dtype.names, h.counts):
        block = values[:, col:col + count]
        records[name] = (block[:, 0] if count == 1 else block).astype(records.dtype[name].base, copy=False)
        col += count
    return records, sum(len(ln) + 1 for ln in lines[h.points:])


def decode_pcd(buf: bytes, source: str = "<pcd>") -> PcdCloud:
    """Decode a whole PCD file held in memory."""
    header = parse_pcd_header(buf, source)
    reader = {"ascii": _records_ascii, "binary": _records_binary, "binary_compressed": _records_compressed}
    records, trailing = reader[header.encoding](buf, header, source)
    pads = {_pad_name(i) for i, name in enumerate(header.fields) if name == "_"}
    columns = {name: np.array(records[name]) for name in records.dtype.names if name not in pads}
    return PcdCloud(header, columns, trailing)


def read_pcd(path: str | Path) -> PcdCloud:
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_DECOMPRESSED_BYTES + MAX_HEADER_BYTES:
            raise _fail(str(path), f"{size} bytes, more than a scan file may hold "
                                   f"({MAX_DECOMPRESSED_BYTES + MAX_HEADER_BYTES})")
        buf = path.read_bytes()
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read PCD file: {exc.strerror or exc}") from exc
    return decode_pcd(buf, str(path))


def encode_pcd(columns: dict[str, np.ndarray], encoding: str = "binary") -> bytes:
    """Encode named (N,) or (N, COUNT) numeric arrays as a PCD v0.7 file (binary_compressed uses literal LZF)."""
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    n = len(arrays[0]) if arrays else 0
    kinds = {"f": "F", "i": "I", "u": "U"}
    dtype = np.dtype([(nm, a.dtype.newbyteorder("<"), a.shape[1:]) for nm, a in zip(names, arrays)])
    records = np.empty(n, dtype)
    for nm, a in zip(names, arrays):
        records[nm] = a
    counts = [int(np.prod(a.shape[1:])) if a.ndim > 1 else 1 for a in arrays]
    header = "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7", "FIELDS " + " ".join(names),
        "SIZE " + " ".join(str(a.dtype.itemsize) for a in arrays),
        "TYPE " + " ".join(kinds[a.dtype.kind] for a in arrays), "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {encoding}", ""]).encode()
    if encoding == "binary":
        return header + records.tobytes()
    if encoding == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(records[nm]).tobytes() for nm in names)
        packed = compress_literal_lzf(raw)
        return header + np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    if encoding == "ascii":
        flat = [a.reshape(n, -1) for a in arrays]
        lines = [" ".join(repr(v.item()) for blk in flat for v in blk[i]) for i in range(n)]
        return header + ("\n".join(lines) + "\n").encode()
    raise ValueError(f"encoding {encoding!r}, expected one of {', '.join(_ENCODINGS)}")


def write_pcd(path: str | Path, columns: dict[str, np.ndarray], encoding: str = "binary") -> None:
    Path(path).write_bytes(encode_pcd(columns, encoding))
