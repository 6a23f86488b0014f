"""One partition per distinct survey cloud: drives that name the same file ingest it each, readers read it once."""
from __future__ import annotations

import hashlib

import numpy as np
import pyarrow as pa

from pipeline.declare import PartitionKey
from pipeline.fingerprint import file_sha256
from pipeline.testing import MemoryInputReader
from schemas import SCHEMAS
from stages.common.survey_parts import distinct_survey_partitions


def survey(drives: list[str]) -> pa.Table:
    n = 5
    return pa.table({"drive": np.repeat(drives, n), "east_m": np.tile(np.arange(n, dtype=float), len(drives)),
                     "north_m": np.zeros(n * len(drives)), "up_m": np.zeros(n * len(drives)),
                     "intensity": np.ones(n * len(drives), np.float32)}, schema=SCHEMAS["survey_enu"])


def test_the_first_partition_of_each_source_and_every_unrecorded_one():
    tables = {"survey": survey(["drive_0", "drive_1", "drive_2", "drive_3"])}
    meta = {"survey": {"partitions": {"drive0": {"survey_sha256": "aa"}, "drive1": {"survey_sha256": "aa"},
                                      "drive2": {"survey_sha256": "bb"}, "drive3": {}}}}
    got = distinct_survey_partitions(MemoryInputReader(tables, meta))
    assert got == [PartitionKey(drive="drive_0"), PartitionKey(drive="drive_2"), PartitionKey(drive="drive_3")]


def test_without_records_every_partition_is_read_as_before():
    reader = MemoryInputReader({"survey": survey(["drive_0", "drive_1"])}, {"survey": {}})
    assert distinct_survey_partitions(reader) == [PartitionKey(drive="drive_0"), PartitionKey(drive="drive_1")]


def test_file_hash_is_the_content_hash(tmp_path):
    data = np.random.default_rng(0).bytes(3 * (1 << 20) + 17)  # more than one read block
    (tmp_path / "a.las").write_bytes(data)
    assert file_sha256(tmp_path / "a.las") == hashlib.sha256(data).hexdigest()
