"""build_once: a value needed by several processes is built by one of them and loaded by the others; the same value
whoever built it; a file that cannot be loaded is built again; no folder builds in place."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline.parallel import build_once, parallel_map
from tests.pipeline.toy_parallel import built_once_value


def test_processes_asking_at_once_build_it_once(tmp_path):
    log = tmp_path / "builds.log"
    out = parallel_map(built_once_value, [(str(tmp_path / "shared"), str(log))] * 4, workers=2)
    assert [v for v, _ in out] == [[1.5, 2.5, 3.5]] * 4
    assert len(log.read_text().split()) == 1  # one build; the other process loaded it
    assert sorted(p.name for p in (tmp_path / "shared").iterdir()) == [".value.json.lock", "value.json"]


def test_a_process_that_finds_it_being_built_waits_and_loads_it(tmp_path):
    import fcntl
    import threading

    got = {}
    with open(tmp_path / ".a.npy.lock", "a+b") as lock:  # another process is building "a.npy"
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        waiter = threading.Thread(target=lambda: got.update(v=build_once(
            tmp_path, "a.npy", lambda: np.zeros(2))))
        waiter.start()
        waiter.join(0.5)
        assert waiter.is_alive() and not got  # waits for the lock instead of building its own
        with open(tmp_path / "a.npy", "wb") as fh:  # the builder writes it, then releases the lock
            np.save(fh, np.arange(4.0))
    waiter.join(10)
    np.testing.assert_array_equal(got["v"], np.arange(4.0))  # loaded, not built


def test_built_then_loaded_in_this_process(tmp_path):
    calls = []

    def build():
        calls.append(1)
        return np.arange(5.0)

    a = build_once(tmp_path, "a.npy", build)
    b = build_once(tmp_path, "a.npy", build)
    np.testing.assert_array_equal(a, b)
    assert len(calls) == 1


def test_a_file_that_cannot_be_loaded_is_built_again(tmp_path, caplog):
    (tmp_path / "a.npy").write_bytes(b"not an array")
    with caplog.at_level(logging.WARNING, logger="pipeline.parallel"):
        got = build_once(tmp_path, "a.npy", lambda: np.arange(3.0))
    np.testing.assert_array_equal(got, np.arange(3.0))
    assert "cannot load" in caplog.text and "a.npy" in caplog.text


def test_without_a_folder_it_builds_every_time(tmp_path):
    calls = []
    for _ in range(2):
        build_once(None, "a.npy", lambda: calls.append(1) or np.zeros(1))
    assert len(calls) == 2 and not any(Path(tmp_path).iterdir())


def test_a_folder_without_advisory_locks_still_builds_and_shares(tmp_path, monkeypatch):
    import errno
    import fcntl

    def no_locks(*_a):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    a = build_once(tmp_path, "a.npy", lambda: np.arange(3.0))
    b = build_once(tmp_path, "a.npy", lambda: np.zeros(3))  # loaded, not built again
    np.testing.assert_array_equal(a, np.arange(3.0))
    np.testing.assert_array_equal(b, np.arange(3.0))
