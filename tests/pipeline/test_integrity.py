"""Issue 22 findings 3, 4 and 8 (YAML): stored intermediates are verified on read, names and derived paths
stay under their root, YAML is parsed with bounded work and duplicate keys are refused."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pyarrow as pa
import pytest
import yaml

from pipeline.errors import ConfigError, IntegrityError, PathEscapeError
from pipeline.names import check_name, inside, name_problem
from pipeline.reader import StoreInputReader
from pipeline.safe_yaml import load_yaml, load_yaml_file
from pipeline.store import write_pieces
from tests.pipeline.test_engine import toy_stages  # noqa: F401 - the toy registry fixture

REPO = Path(__file__).resolve().parents[2]
SCHEMA = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float64())])


def _dataset(root: Path, drive: str = "d0") -> tuple[StoreInputReader, list[dict]]:
    out = root / "datasets" / "toy" / "fp1"
    table = pa.table({"drive": [drive] * 50, "scan_id": list(range(50)), "x_m": [float(i) for i in range(50)]},
                     schema=SCHEMA)
    files = write_pieces(table, out_dir=out, label="p0", schema=SCHEMA, partitioning=("drive",), where="test")
    (out / "_manifest.json").write_text(json.dumps({"fingerprint": "fp1", "files": files}))
    return StoreInputReader(root, {"toy": ("toy", "fp1")}, {"toy": SCHEMA}), files


def test_finding3_a_flipped_bit_in_an_intermediate_is_refused_on_read(tmp_path):
    reader, files = _dataset(tmp_path)
    assert reader.read("toy").num_rows == 50 and files[0]["sha256"]
    path = tmp_path / "datasets" / "toy" / "fp1" / files[0]["path"]
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0x04
    path.write_bytes(bytes(raw))
    fresh = StoreInputReader(tmp_path, {"toy": ("toy", "fp1")}, {"toy": SCHEMA})
    for read in (lambda: fresh.read("toy"), lambda: fresh.read_in("toy", "scan_id", [3])):
        with pytest.raises(IntegrityError, match="sha256"):
            read()


def test_a_file_altered_between_two_reads_of_one_reader_is_refused_at_the_second(tmp_path):
    """The reader keeps its files' resolved paths between reads, not their verification."""
    reader, files = _dataset(tmp_path)
    assert reader.read_in("toy", "scan_id", [3]).num_rows == 1
    path = tmp_path / "datasets" / "toy" / "fp1" / files[0]["path"]
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0x04
    time.sleep(0.01)  # a new mtime
    path.write_bytes(bytes(raw))
    for read in (lambda: reader.read("toy"), lambda: reader.read_in("toy", "scan_id", [3])):
        with pytest.raises(IntegrityError, match="sha256"):
            read()


def test_finding4_partition_values_and_manifest_paths_cannot_escape(tmp_path):
    with pytest.raises(PathEscapeError):
        _dataset(tmp_path, drive="../../../../escaped")
    assert not (tmp_path.parent / "escaped").exists()
    reader, files = _dataset(tmp_path / "ok")
    manifest = tmp_path / "ok" / "datasets" / "toy" / "fp1" / "_manifest.json"
    manifest.write_text(json.dumps({"fingerprint": "fp1", "files": [{**files[0], "path": "../../../../../x.parquet"}]}))
    with pytest.raises(PathEscapeError):
        StoreInputReader(tmp_path / "ok", {"toy": ("toy", "fp1")}, {"toy": SCHEMA}).read("toy")


@pytest.mark.parametrize("name", ["../evil", "..", ".", "", "a/b", "a\\b", "-rf", ".hidden", "x" * 65, "a..b",
                                  "tab\t", "caf\u00e9", None, 3])
def test_names_outside_the_pattern_are_refused(name):
    assert name_problem(name, "drive") is not None
    with pytest.raises(ConfigError, match="not allowed"):
        check_name(name, "map")


@pytest.mark.parametrize("name", ["drive_0", "gangnam", "kitti-0048.city", "A", "x" * 64])
def test_names_in_the_pattern_pass(name):
    assert check_name(name, "drive") == name


def test_inside_resolves_dotdot_and_symlinks(tmp_path):
    assert inside(tmp_path, "a", "b.txt") == (tmp_path / "a" / "b.txt").resolve()
    for parts in (("..", "x"), ("a/../../x",), ("/etc/passwd",)):
        with pytest.raises(PathEscapeError):
            inside(tmp_path, *parts)
    (tmp_path / "link").symlink_to("/")
    with pytest.raises(PathEscapeError):
        inside(tmp_path, "link", "etc")


def _workflow(tmp_path: Path, **changes) -> Path:
    doc = yaml.safe_load((REPO / "workflows" / "tiny.yaml").read_text())
    doc["catalog"] = [str(REPO / "data_catalog")]
    doc.update(changes)
    path = tmp_path / "wf.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_finding4_workflow_drive_and_map_names_must_match_the_pattern(tmp_path):
    from pipeline.workflow import load_workflow

    doc = yaml.safe_load((REPO / "workflows" / "tiny.yaml").read_text())
    drives = [dict(d) for d in doc.get("drives", [])] or [{"name": "x", "path": "x/drive.yaml"}]
    drives[0]["name"] = "../../outside"
    with pytest.raises(ConfigError) as info:
        load_workflow(_workflow(tmp_path, drives=drives, map_name="../../evil"))
    text = str(info.value)
    assert "drive name '../../outside'" in text and "map name '../../evil'" in text


def test_finding8_duplicate_keys_are_refused_with_file_line_and_key(tmp_path):
    with pytest.raises(ConfigError, match=r"(?s)f.yaml.*line 3.*duplicate key 'tile_size_m' \(first on line 1\)"):
        load_yaml("tile_size_m: 100\nname: a\ntile_size_m: 50\n", "f.yaml")
    with pytest.raises(ConfigError, match="duplicate key 'b'"):
        load_yaml("a:\n  b: 1\n  c: 2\n  b: 3\n", "nested.yaml")
    path = _workflow(tmp_path)
    path.write_text(path.read_text() + "name: again\n")
    from pipeline.workflow import load_workflow

    with pytest.raises(ConfigError, match="duplicate key 'name'"):
        load_workflow(path)


def test_finding5_an_alias_bomb_is_refused_at_once(tmp_path):
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n" for p, c in zip("abcdefgh", "bcdefghi"))
    path = tmp_path / "bomb.yaml"
    path.write_text(bomb)
    start = time.perf_counter()
    with pytest.raises(ConfigError, match="alias"):
        load_yaml_file(path)
    assert time.perf_counter() - start < 5.0  # generous: the old parser ran 30 s and 3 GB before failing


def test_yaml_size_cap_and_non_utf8(tmp_path):
    with pytest.raises(ConfigError, match="limit"):
        load_yaml("a: " + "x" * 100, "big.yaml", max_bytes=50)
    path = tmp_path / "latin1.yaml"
    path.write_bytes("name: caf\u00e9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_yaml_file(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_yaml_file(tmp_path / "missing.yaml")
    assert load_yaml("a: &x 1\nb: [1, 2]\n", "anchors.yaml") == {"a": 1, "b": [1, 2]}


def test_catalog_schema_references_cannot_import_arbitrary_modules(tmp_path):
    from pipeline.catalog import load_catalog

    (tmp_path / "c.yaml").write_text(
        "datasets:\n  evil:\n    schema: 'os:system'\n  bad:\n    schema: 'antigravity:x'\n"
    )
    with pytest.raises(ConfigError) as info:
        load_catalog([tmp_path / "c.yaml"])
    assert str(info.value).count("may only name a module of the schemas package") == 2
    import sys

    assert "antigravity" not in sys.modules


def _hash_calls(monkeypatch) -> list:
    import pipeline.store as store

    calls, real = [], store.file_sha256
    monkeypatch.setattr(store, "file_sha256", lambda path, *a: calls.append(Path(path).name) or real(path, *a))
    return calls


def _another_process(monkeypatch) -> None:
    """What a fresh process of the same run sees: no file verified by itself yet."""
    import pipeline.store as store

    monkeypatch.setattr(store, "_VERIFIED", {})


def test_a_file_written_or_verified_in_a_run_is_hashed_once_in_that_run_whatever_the_process(tmp_path, monkeypatch):
    calls = _hash_calls(monkeypatch)
    ledger = tmp_path / "root" / "tmp" / "verified-run1"
    out = tmp_path / "root" / "datasets" / "toy" / "fp1"
    table = pa.table({"drive": ["d0"] * 5, "scan_id": list(range(5)), "x_m": [0.0] * 5}, schema=SCHEMA)
    files = write_pieces(table, out_dir=out, label="p0", schema=SCHEMA, partitioning=("drive",), where="test",
                         ledger=ledger)
    (out / "_manifest.json").write_text(json.dumps({"fingerprint": "fp1", "files": files}))
    assert len(calls) == 1  # the writer's own hash
    _another_process(monkeypatch)
    reader = StoreInputReader(tmp_path / "root", {"toy": ("toy", "fp1")}, {"toy": SCHEMA}, ledger=ledger)
    assert reader.read("toy").num_rows == 5 and len(calls) == 1  # trusted: the writer hashed it in this run
    _another_process(monkeypatch)
    unledgered = StoreInputReader(tmp_path / "root", {"toy": ("toy", "fp1")}, {"toy": SCHEMA})
    assert unledgered.read("toy").num_rows == 5 and len(calls) == 2  # no run's ledger: hashed
    _another_process(monkeypatch)
    next_run = StoreInputReader(tmp_path / "root", {"toy": ("toy", "fp1")}, {"toy": SCHEMA},
                                ledger=tmp_path / "root" / "tmp" / "verified-run2")
    assert next_run.read("toy").num_rows == 5 and len(calls) == 3  # another run verifies again ...
    _another_process(monkeypatch)
    import pickle

    shipped = pickle.loads(pickle.dumps(next_run))  # ... once: a reader handed to a worker process keeps the ledger
    assert shipped.read("toy").num_rows == 5 and len(calls) == 3


def test_a_file_altered_after_its_ledger_entry_is_hashed_again_and_refused(tmp_path, monkeypatch):
    ledger = tmp_path / "tmp" / "verified-run1"
    _, files = _dataset(tmp_path)
    _another_process(monkeypatch)
    reader = StoreInputReader(tmp_path, {"toy": ("toy", "fp1")}, {"toy": SCHEMA}, ledger=ledger)
    assert reader.read("toy").num_rows == 50 and any(ledger.iterdir())  # verified by this process: entered
    path = tmp_path / "datasets" / "toy" / "fp1" / files[0]["path"]
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0x04
    time.sleep(0.01)  # a new mtime
    path.write_bytes(bytes(raw))
    _another_process(monkeypatch)
    fresh = StoreInputReader(tmp_path, {"toy": ("toy", "fp1")}, {"toy": SCHEMA}, ledger=ledger)
    with pytest.raises(IntegrityError, match="sha256"):
        fresh.read("toy")


def test_a_run_verifies_through_its_own_ledger_and_removes_it(tmp_path, toy_stages):  # noqa: F811 - the fixture
    from tests.pipeline.test_engine import read_output, run, write_toy

    path = write_toy(tmp_path)
    run(path, root=tmp_path / "r", scheduler="local", workers=2)
    assert read_output(tmp_path / "r", "toy_total").num_rows > 0
    assert not list((tmp_path / "r" / "tmp").glob("verified-*"))
