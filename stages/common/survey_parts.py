"""Which partitions of ``survey_enu`` to read: one per distinct survey cloud.

Every drive file may name the workflow's survey cloud (a drive folder is self-contained), so ingest writes one
``survey_enu`` partition per drive, and drives that share a cloud write the same points again. Ingest records each
partition's source (``survey_sha256``: the cloud file's content hash, ``pipeline.fingerprint.file_sha256``, in the
partition's manifest extra); readers take the first partition of each source, so a map built from N drives sharing
one survey reads it once, not N times (memory, time, and per-cell point counts that do not depend on how many drives
named the cloud). Partitions committed without the record (older roots) are all read, as before.
"""
from __future__ import annotations

from pipeline.declare import InputReader, PartitionKey


def distinct_survey_partitions(inputs: InputReader, arg: str = "survey") -> list[PartitionKey]:
    """The partitions of ``arg`` to read: the first (in partition order) of each recorded survey source, and every
    partition without a record."""
    extras = inputs.metadata(arg).get("partitions", {}) or {}
    seen: set[str] = set()
    out = []
    for key in inputs.partitions(arg):
        source = (extras.get(key.label) or {}).get("survey_sha256")
        if source is not None:
            if source in seen:
                continue
            seen.add(source)
        out.append(key)
    return out
