"""``mapservice.rebuild.held_solution``: what an incremental rebuild holds, read from LATEST's manifest."""
from __future__ import annotations

import json

from mapservice.rebuild import held_solution
from pipeline import storage
from pipeline.store import dataset_dir
from pipeline.versioned import publish_version

FP = "ab" * 32


def _publish(mdir, inputs):
    def write(staging):
        (staging / "x.txt").write_text("x")
        return {"inputs": inputs}

    return publish_version(mdir, write, durable=False)


def _commit_poses(root, fp):
    ddir = dataset_dir(root, "poses_optimized", fp)
    ddir.mkdir(parents=True)
    storage.dataset_manifest(ddir).write_text(json.dumps({"fingerprint": fp, "files": []}))


def test_latest_s_poses_are_held_while_committed(tmp_path):
    root = tmp_path
    mdir = storage.map_dir(root, "city")
    assert held_solution(root, mdir) is None  # no map yet: the joint solve
    mdir.mkdir(parents=True)
    _publish(mdir, {"poses": {"dataset": "poses_optimized", "fingerprint": FP}})
    assert held_solution(root, mdir) is None  # named, but not committed (gc removed it): the joint solve
    _commit_poses(root, FP)
    assert held_solution(root, mdir) == {"fingerprint": FP, "version": 1}
    _publish(mdir, {"corner_map": {"dataset": "corner_map", "fingerprint": FP}})
    assert held_solution(root, mdir) is None  # a version that names no poses: nothing to hold
