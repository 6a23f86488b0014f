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


def test_pieces_written_by_several_threads_keep_their_order_and_at_most_that_many_wait(tmp_path, monkeypatch):
    """Writes slowed down so that they overlap: the records come in the pieces' order with their own rows, at most
    ``WRITE_THREADS`` writes run at once, and a failing write raises its error once the earlier ones are in."""
    import time

    import pyarrow.parquet as pq

    import pipeline.store as store

    schema = pa.schema([("drive", pa.string()), ("scan_id", pa.int64())])
    tables = [pa.table({"drive": ["d0"] * (k + 1), "scan_id": list(range(k + 1))}, schema=schema) for k in range(9)]
    real = store.write_parquet_atomic
    running, most = [0], [0]
    lock = threading.Lock()

    def slow(table, path):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.05 if table.num_rows % 2 else 0.01)  # odd pieces finish after the even ones started later
        try:
            if table.num_rows == 7:
                raise store.DatasetIOError(f"cannot write {path}: disk full")
            return real(table, path)
        finally:
            with lock:
                running[0] -= 1

    monkeypatch.setattr(store, "write_parquet_atomic", slow)
    kw = dict(label="p0", schema=schema, partitioning=(), where="test")
    records = write_pieces((t for t in tables[:6]), out_dir=tmp_path / "a", **kw)
    assert [r["rows"] for r in records] == [1, 2, 3, 4, 5, 6]
    assert [pq.read_table(tmp_path / "a" / r["path"]).num_rows for r in records] == [1, 2, 3, 4, 5, 6]
    assert 2 <= most[0] <= store.WRITE_THREADS
    with pytest.raises(store.DatasetIOError, match="disk full"):
        write_pieces((t for t in tables), out_dir=tmp_path / "b", **kw)
