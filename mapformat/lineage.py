"""The committed datasets a published map version was built from, found through the fingerprints it records.

A version's manifest records each input of the tiles stage as ``{dataset, fingerprint}`` (``inputs``); every
committed dataset's ``_manifest.json`` records its own inputs the same way, and a stage writes all its outputs
under the one fingerprint of its run (``ROOT/datasets/<dataset>/<fp16>``). So the scans a version's poses were
optimised from are the ``scans_raw`` its ``poses`` input's manifest names, and the outputs of one stage run are
siblings under the same fingerprint (``mapservice/gc.py`` keeps them together for the same reason).

An export that needs more than the version directory (the Autoware point cloud: scans, poses, extrinsics) asks a
``VersionLineage`` for them: it walks the recorded inputs breadth-first from the version's and never looks for the
newest committed data of a name, so a later build in the same root (another map, more drives, a drive of the same
name) changes nothing it reads. What the lineage names but the root no longer holds (removed by ``gc``, or the
map was built in another root) is a one-line ``DatasetIOError`` naming the dataset and fingerprint.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from pipeline.errors import DatasetIOError
from pipeline.names import inside
from pipeline.storage import datasets_dir
from pipeline.store import FP_LEN, DataRoot, data_root, verify_file


@dataclass(frozen=True)
class Committed:
    """One committed dataset of the lineage: its directory and manifest."""

    dataset: str
    fingerprint: str  # as recorded (full length)
    path: Path  # local: on an object-store root, the local copy's directory
    manifest: dict[str, Any]
    source: DataRoot | None = None  # the root it was found in (an object store: files are fetched from it)

    def files(self, drive: str | None = None) -> list[Path]:
        """The dataset's files (of ``drive``), confined to its directory and sha256-verified against the manifest
        (on an object-store root, downloaded into the local copy first)."""
        recs = [rec for rec in self.manifest.get("files", [])
                if drive is None or (rec.get("partition") or {}).get("drive") == drive]
        if self.source is not None:
            self.source.fetch(self.dataset, self.fingerprint, [(r["path"], r.get("bytes")) for r in recs])
        out = []
        for rec in recs:
            path = inside(self.path, rec["path"])
            verify_file(path, rec.get("sha256"), self.dataset)
            out.append(path)
        return out


class VersionLineage:
    """The datasets reachable from a version's recorded inputs under ``root`` (breadth-first, nearest first)."""

    def __init__(self, root: "Path | str", version_manifest: dict[str, Any], label: str):
        self.source = data_root(root if isinstance(root, str) and "://" in root else Path(root))
        self.root, self.label = self.source.uri, label
        inputs = version_manifest.get("inputs")
        if not isinstance(inputs, dict) or not inputs:
            raise DatasetIOError(f"{label}: its manifest records no inputs, so the datasets it was built from cannot "
                                 "be named; hint: rebuild the map to publish a version that records them")
        self._start = [(str(v.get("dataset")), str(v.get("fingerprint")))
                       for _, v in sorted(inputs.items()) if isinstance(v, dict) and v.get("fingerprint")]
        self._nodes: list[Committed] | None = None
        self.missing: list[tuple[str, str]] = []  # recorded but not committed under root

    def _walk(self) -> list[Committed]:
        if self._nodes is not None:
            return self._nodes
        nodes, seen, queue = [], set(), deque(self._start)
        while queue:
            dataset, fp = queue.popleft()
            if (dataset, fp[:FP_LEN]) in seen:
                continue
            seen.add((dataset, fp[:FP_LEN]))
            manifest = self.source.manifest(dataset, fp)
            if manifest is None:
                self.missing.append((dataset, fp))
                continue
            nodes.append(Committed(dataset, fp, self.source.dir(dataset, fp), manifest, self.source))
            for v in (manifest.get("inputs") or {}).values():
                if isinstance(v, dict) and v.get("fingerprint"):
                    queue.append((str(v["dataset"]), str(v["fingerprint"])))
        self._nodes = nodes
        return nodes

    def _sibling(self, node: Committed, dataset: str) -> Committed | None:
        """``dataset`` written by the same stage run as ``node`` (same stage, same fingerprint), if committed."""
        m = self.source.manifest(dataset, node.fingerprint)
        if m is None or m.get("stage") != node.manifest.get("stage") \
                or str(m.get("fingerprint", ""))[:FP_LEN] != node.fingerprint[:FP_LEN]:
            return None
        return Committed(dataset, str(m["fingerprint"]), self.source.dir(dataset, node.fingerprint), m, self.source)

    def candidates(self, dataset: str) -> list[Committed]:
        """Every committed ``dataset`` of the lineage, nearest the version first (unique by fingerprint)."""
        out: dict[str, Committed] = {}
        for node in self._walk():
            hit = node if node.dataset == dataset else self._sibling(node, dataset)
            if hit is not None:
                out.setdefault(hit.fingerprint[:FP_LEN], hit)
        return list(out.values())

    def find(self, dataset: str, drive: str | None = None) -> Committed:
        """The nearest committed ``dataset`` of the lineage (holding rows of ``drive`` when given)."""
        found = self.candidates(dataset)
        if drive is not None:
            found = [c for c in found if any((r.get("partition") or {}).get("drive") == drive
                                             for r in c.manifest.get("files", []))]
        if found:
            return found[0]
        what = f"{dataset}" + (f" of drive {drive!r}" if drive is not None else "")
        gone = ", ".join(f"{d} {fp[:FP_LEN]}" for d, fp in self.missing[:3])
        gone += f" and {len(self.missing) - 3} more" if len(self.missing) > 3 else ""
        where = self.source.store.url(datasets_dir(self.source.store.root))
        why = (f"; recorded but not committed under {where}: {gone} (removed by gc, or the "
               "map was built in another root)") if gone else ""
        raise DatasetIOError(f"{self.label}: no committed {what} among the datasets it was built from{why}; hint: "
                             "export from the root that built this version (--root), or rebuild it")

    def read(self, dataset: str, drive: str, columns: list[str] | None = None):
        """``dataset``'s rows of ``drive`` (one table)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        c = self.find(dataset, drive)
        return pa.concat_tables([pq.read_table(f, columns=columns) for f in c.files(drive)])

    def rows(self, dataset: str, drive: str) -> int:
        """How many rows of ``drive`` ``dataset`` holds (the files' Parquet footers; nothing else is read)."""
        import pyarrow.parquet as pq

        return sum(pq.ParquetFile(f).metadata.num_rows for f in self.find(dataset, drive).files(drive))

    def batches(self, dataset: str, drive: str, columns: list[str], batch_rows: int) -> Iterator[Any]:
        """``dataset``'s rows of ``drive`` as record batches of at most ``batch_rows`` (streamed file by file)."""
        import pyarrow.parquet as pq

        for f in self.find(dataset, drive).files(drive):
            yield from pq.ParquetFile(f).iter_batches(batch_size=batch_rows, columns=columns)
