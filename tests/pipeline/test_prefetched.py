"""A streamed output is produced one piece ahead of the store's writes, in order, with the producer's errors raised
where they happened and the producer stopped when the writes stop."""
from __future__ import annotations

import threading

import pyarrow as pa
import pytest

from pipeline.store import prefetched, write_pieces


def test_pieces_come_in_order_and_all_of_them():
    assert list(prefetched(iter(range(50)))) == list(range(50))
    assert list(prefetched(iter([]))) == []


def test_the_next_piece_is_produced_while_the_caller_works_on_this_one():
    """The caller holds piece 0 until the producer has started piece 1: without the thread this would wait forever
    (bounded here by a timeout that fails the test)."""
    started = {k: threading.Event() for k in range(3)}

    def produce():
        for k in range(3):
            started[k].set()
            yield k

    it = prefetched(produce())
    assert next(it) == 0
    assert started[1].wait(timeout=5.0), "piece 1 was not produced while piece 0 was being written"
    assert list(it) == [1, 2]


def test_a_producer_error_is_raised_at_the_piece_it_failed_on():
    def produce():
        yield 1
        yield 2
        raise ValueError("scan 7 of drive_0: truncated file")

    got = []
    with pytest.raises(ValueError, match="scan 7 of drive_0"):
        for x in prefetched(produce()):
            got.append(x)
    assert got == [1, 2]


def test_when_the_caller_stops_the_producer_stops_and_its_generator_is_closed():
    closed = threading.Event()
    produced = []

    def produce():
        try:
            for k in range(1000):
                produced.append(k)
                yield k
        finally:
            closed.set()

    it = prefetched(produce())
    assert next(it) == 0
    it.close()  # the caller gave up (a write failed)
    assert closed.wait(timeout=5.0)
    assert len(produced) <= 3  # the piece handed out, at most one waiting, at most one in the making


def test_write_pieces_of_a_generator_equal_those_of_a_list(tmp_path):
    import pyarrow.parquet as pq

    schema = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float32())])
    tables = [pa.table({"drive": [d] * 5, "scan_id": list(range(5 * k, 5 * k + 5)),
                        "x_m": pa.array([float(k)] * 5, pa.float32())}, schema=schema)
              for k, d in enumerate(["d0", "d0", "d1", "d0"])]
    kw = dict(label="p0", schema=schema, partitioning=("drive",), where="test")
    from_list = write_pieces(tables, out_dir=tmp_path / "a", **kw)
    from_gen = write_pieces((t for t in tables), out_dir=tmp_path / "b", **kw)
    assert [(r["path"], r["rows"], r["partition"]) for r in from_list] == \
        [(r["path"], r["rows"], r["partition"]) for r in from_gen]
    for a, b in zip(from_list, from_gen):
        assert pq.read_table(tmp_path / "a" / a["path"]).equals(pq.read_table(tmp_path / "b" / b["path"]))


def test_pieces_written_at_once_keep_their_order_and_a_failed_write_leaves_no_file(tmp_path, monkeypatch):
    """Several pieces in the write threads at once: the records come in piece order with each file's own rows
    and checksum; a write that fails raises its error after the others end, and no data file is left of it."""
    import threading
    import time

    import pyarrow.parquet as pq

    from pipeline import store
    from pipeline.errors import DatasetIOError
    from pipeline.fingerprint import file_sha256

    monkeypatch.setattr("pipeline.parallel.default_workers", lambda: 4)
    monkeypatch.setattr(store, "WRITE_THREADS", 3)
    schema = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float32())])
    tables = [pa.table({"drive": ["d0"] * (k + 1), "scan_id": list(range(k + 1)),
                        "x_m": pa.array([float(k)] * (k + 1), pa.float32())}, schema=schema) for k in range(8)]
    real = store.write_parquet_atomic
    active, most = [0], [0]
    lock = threading.Lock()

    def slow(table, path):
        with lock:
            active[0] += 1
            most[0] = max(most[0], active[0])
        time.sleep(0.05 * (8 - table.num_rows))  # the first pieces finish last
        try:
            return real(table, path)
        finally:
            with lock:
                active[0] -= 1

    monkeypatch.setattr(store, "write_parquet_atomic", slow)
    kw = dict(label="p0", schema=schema, partitioning=("drive",), where="test")
    recs = store.write_pieces((t for t in tables), out_dir=tmp_path / "a", **kw)
    assert most[0] > 1  # written at once
    assert [r["rows"] for r in recs] == list(range(1, 9))
    for r in recs:
        path = tmp_path / "a" / r["path"]
        assert pq.read_table(path)["x_m"][0].as_py() == r["rows"] - 1 and r["sha256"] == file_sha256(path)

    def failing(table, path):
        if table.num_rows == 3:
            raise DatasetIOError(f"cannot write {path}: disk full")
        return slow(table, path)

    monkeypatch.setattr(store, "write_parquet_atomic", failing)
    with pytest.raises(DatasetIOError, match="disk full"):
        store.write_pieces((t for t in tables), out_dir=tmp_path / "b", **kw)
    assert active[0] == 0  # the other writes ended before the error left
    assert "part-p0-00002.parquet" not in {p.name for p in (tmp_path / "b").rglob("*.parquet")}
