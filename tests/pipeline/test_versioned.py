"""pipeline.versioned: immutable versions, atomic LATEST, exclusive publisher, crash safety, retention."""
from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import ChecksumError, PublishConflictError, UnknownNameError
from pipeline.versioned import (
    LATEST_NAME,
    apply_retention,
    check_version,
    list_versions,
    parse_version,
    publish_lock,
    publish_version,
    read_latest,
    read_manifest,
    resolve_version,
    verify_version,
    version_name,
    write_latest,
)

REPO = Path(__file__).resolve().parents[2]


def _writer(payload: dict[str, bytes], fields: dict | None = None):
    def write(staging: Path) -> dict:
        for rel, data in payload.items():
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            (staging / rel).write_bytes(data)
        return dict(fields or {"kind": "test"})
    return write


def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith((".staging-", ".trash-", ".LATEST.tmp")))


def test_publish_read_republish(tmp_path):
    d = tmp_path / "maps" / "city"
    v1 = publish_version(d, _writer({"a.txt": b"one", "sub/b.bin": b"\x00\x01"}, {"kind": "test", "n": 1}),
                         durable=False)
    assert (v1.version, v1.created, v1.path.name) == (1, True, "v0001")
    assert read_latest(d) == 1 and (d / LATEST_NAME).read_text() == f"v0001 {v1.manifest_sha256}\n"
    manifest, sha = read_manifest(v1.path)
    assert sha == v1.manifest_sha256 and manifest["n"] == 1 and manifest["parent_version"] is None
    assert set(manifest["files"]) == {"a.txt", "sub/b.bin"}
    assert verify_version(v1.path) == []
    v2 = publish_version(d, _writer({"a.txt": b"two"}), durable=False)
    assert (v2.version, v2.manifest["parent_version"]) == (2, 1)
    assert list_versions(d) == [1, 2] and read_latest(d) == 2
    assert (v1.path / "a.txt").read_bytes() == b"one"  # the old version is untouched
    assert resolve_version(d, "v1") == v1.path and resolve_version(d, "LATEST") == v2.path
    assert _leftovers(d) == []


def test_reuse_returns_latest_without_publishing(tmp_path):
    d = tmp_path / "m"
    publish_version(d, _writer({"x": b"1"}, {"fp": "abc"}), durable=False)
    again = publish_version(d, _writer({"x": b"2"}), reuse=lambda m: m.get("fp") == "abc", durable=False)
    assert (again.version, again.created) == (1, False) and list_versions(d) == [1]


def test_failed_writer_leaves_nothing_and_latest_unchanged(tmp_path):
    d = tmp_path / "m"
    publish_version(d, _writer({"x": b"1"}), durable=False)

    def boom(staging: Path) -> dict:
        (staging / "half.bin").write_bytes(b"partial")
        raise RuntimeError("writer died")

    with pytest.raises(RuntimeError, match="writer died"):
        publish_version(d, boom, durable=False)
    assert read_latest(d) == 1 and list_versions(d) == [1] and _leftovers(d) == []


def test_writer_may_not_write_the_manifest_or_reserved_keys(tmp_path):
    with pytest.raises(OSError, match="manifest.json"):
        publish_version(tmp_path / "m", _writer({"manifest.json": b"{}"}), durable=False)
    with pytest.raises(ValueError, match="reserved"):
        publish_version(tmp_path / "m", _writer({"x": b"1"}, {"files": 3}), durable=False)
    assert read_latest(tmp_path / "m") is None and _leftovers(tmp_path / "m") == []


def test_never_overwrites_an_existing_version_directory(tmp_path):
    d = tmp_path / "m"
    publish_version(d, _writer({"x": b"1"}), durable=False)
    (d / "v0002").mkdir()  # a stray directory someone made by hand
    (d / "v0002" / "keep.txt").write_text("mine")
    v = publish_version(d, _writer({"x": b"3"}), durable=False)
    assert v.version == 3 and (d / "v0002" / "keep.txt").read_text() == "mine"


def test_second_publisher_in_process_conflicts_and_creates_nothing(tmp_path):
    d = tmp_path / "m"
    with publish_lock(d):
        with pytest.raises(PublishConflictError, match="another publisher"):
            publish_version(d, _writer({"x": b"1"}), durable=False)
    assert list_versions(d) == [] and read_latest(d) is None and _leftovers(d) == []


def test_retention_keeps_last_n_and_never_the_latest(tmp_path):
    d = tmp_path / "m"
    for k in range(4):
        publish_version(d, _writer({"x": str(k).encode()}), keep_last=2, durable=False)
    assert list_versions(d) == [3, 4] and read_latest(d) == 4
    for k in range(2):
        publish_version(d, _writer({"x": str(k).encode()}), durable=False)
    write_latest(d, 3, durable=False)  # rolled back by hand to an old version
    apply_retention(d, keep_last=2)
    assert list_versions(d) == [3, 5, 6] and read_latest(d) == 3 and _leftovers(d) == []


def test_verify_detects_flipped_byte_missing_and_extra_files(tmp_path):
    v = publish_version(tmp_path / "m", _writer({"a.bin": bytes(range(256)), "b.txt": b"hello"}), durable=False)
    path = v.path / "a.bin"
    data = bytearray(path.read_bytes())
    data[137] ^= 0x01
    path.write_bytes(bytes(data))
    (v.path / "extra.txt").write_text("x")
    (v.path / "b.txt").unlink()
    problems = verify_version(v.path)
    assert len(problems) == 3
    assert any("a.bin" in p and "sha256" in p for p in problems)
    assert any("b.txt" in p and "missing" in p for p in problems)
    assert any("extra.txt" in p and "not listed" in p for p in problems)
    with pytest.raises(ChecksumError, match="3 problem"):
        check_version(v.path)


def test_version_names_and_unknown_versions(tmp_path):
    assert [parse_version(x) for x in ("v0003", "v3", "3", 3)] == [3, 3, 3, 3]
    assert version_name(12) == "v0012"
    with pytest.raises(UnknownNameError):
        parse_version("latest-ish")
    with pytest.raises(UnknownNameError, match="nothing published"):
        resolve_version(tmp_path / "m", "LATEST")
    publish_version(tmp_path / "m", _writer({"x": b"1"}), durable=False)
    with pytest.raises(UnknownNameError, match="have v0001"):
        resolve_version(tmp_path / "m", "v7")


def test_reader_during_publishes_sees_only_complete_versions(tmp_path):
    d = tmp_path / "m"
    publish_version(d, _writer({f"f{k}": b"0" for k in range(20)}), durable=False)
    seen, errors, stop = set(), [], threading.Event()

    def read_loop():
        while not stop.is_set():
            vdir = resolve_version(d, "LATEST")
            problems = verify_version(vdir)
            if problems:
                errors.append(problems)
            seen.add(vdir.name)

    reader = threading.Thread(target=read_loop)
    reader.start()
    try:
        for k in range(1, 8):
            publish_version(d, _writer({f"f{m}": str(k).encode() * 1000 for m in range(20)}), durable=False)
    finally:
        stop.set()
        reader.join()
    assert errors == [] and len(seen) >= 1


_CHILD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from pipeline.errors import PublishConflictError
    from pipeline.versioned import publish_version
    d, start_at, hold_s, tag = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
    while time.time() < start_at:
        time.sleep(0.001)
    def write(staging):
        for k in range(30):
            (staging / f"f{k:02d}.bin").write_bytes(tag.encode() * 4096)
        time.sleep(hold_s)
        return {"tag": tag}
    try:
        v = publish_version(d, write, durable=False)
        print("WON", v.version)
    except PublishConflictError as exc:
        print("LOST", exc)
        sys.exit(17)
""")


def _spawn(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _CHILD, *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_two_publisher_processes_one_wins_other_leaves_nothing(tmp_path):
    d = tmp_path / "m"
    start_at = time.time() + 2.0
    procs = [_spawn([str(d), str(start_at), "1.0", tag]) for tag in ("A", "B")]
    outs = [p.communicate(timeout=60) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 17], outs
    loser = outs[[p.returncode for p in procs].index(17)]
    assert "another publisher" in loser[0]
    assert list_versions(d) == [1] and read_latest(d) == 1 and _leftovers(d) == []
    assert verify_version(d / "v0001") == []


_LOOP_CHILD = textwrap.dedent("""
    import sys
    from pathlib import Path
    from pipeline.versioned import publish_version
    d = Path(sys.argv[1])
    print("ready", flush=True)
    k = 0
    while True:
        k += 1
        def write(staging, k=k):
            for m in range(40):
                (staging / f"d{m % 4}").mkdir(exist_ok=True)
                (staging / f"d{m % 4}" / f"f{m:02d}.bin").write_bytes(bytes([k % 256]) * 20000)
            return {"k": k}
        publish_version(d, write, keep_last=3, durable=True)
""")


def test_sigkilled_publisher_never_leaves_latest_on_an_incomplete_version(tmp_path):
    d = tmp_path / "m"
    rng = np.random.default_rng(20240611)
    for delay_s in rng.uniform(0.15, 0.9, size=6):
        proc = subprocess.Popen([sys.executable, "-c", _LOOP_CHILD, str(d)], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "ready"  # the kill delays count from the publishing loop's start
        time.sleep(float(delay_s))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        assert proc.returncode == -signal.SIGKILL, proc.stderr.read()
        latest = read_latest(d)
        if latest is not None:
            check_version(d / version_name(latest))  # complete and intact
        for v in list_versions(d):
            assert verify_version(d / version_name(v)) == []  # a vNNNN directory is always complete
    assert read_latest(d) is not None, "no publish completed in any run; lengthen the delays"
    v = publish_version(d, _writer({"x": b"after"}), durable=False)  # cleans leftovers of the killed ones
    assert read_latest(d) == v.version and _leftovers(d) == []
