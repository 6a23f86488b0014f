"""Shared fixtures: the real samples in ../shared/data (skipped with a reason when absent)."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real LiDAR samples not found at {SHARED_DATA} (../shared/data beside the clone)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


_CHECKED: set[tuple[str, int]] = set()  # (manifest path, mtime_ns) already validated in this worker


def published_documents_problems(base: Path) -> list[str]:
    """Every intact map version under ``base`` (``*/maps/NAME/vNNNN`` up to three folders deep; intact: its files
    match its manifest and the digest chain, ``mapformat.verify``) checked against the map format's JSON Schemas:
    its manifest.json, its changelog.json, and the map's map.json when the identity reads. Versions a test broke
    on purpose fail verification and are left alone."""
    from mapformat.schemas import problems
    from mapformat.verify import verify_map
    from mapservice.maps import read_identity
    from pipeline.errors import CornermapError
    from pipeline.versioned import read_manifest, trusted_manifest_digests

    out = []
    patterns = [f"{'*/' * depth}maps/*/v[0-9][0-9][0-9][0-9]*/manifest.json" for depth in range(4)]
    for manifest_path in sorted({p for pat in patterns for p in base.glob(pat)}):
        key = (str(manifest_path), manifest_path.stat().st_mtime_ns)
        if key in _CHECKED:
            continue
        _CHECKED.add(key)
        vdir = manifest_path.parent
        try:
            if verify_map(vdir, trusted_manifest_digests(vdir.parent).get(int(vdir.name[1:]))):
                continue
            manifest = read_manifest(vdir)[0]
            ident = read_identity(vdir.parent)
        except (CornermapError, OSError, ValueError):
            continue
        out += [f"{manifest_path}: {p}" for p in problems(manifest, "manifest")]
        if manifest.get("changelog"):
            import json

            doc = json.loads((vdir / manifest["changelog"]).read_text(encoding="utf-8"))
            out += [f"{vdir / manifest['changelog']}: {p}" for p in problems(doc, "changelog")]
        if ident is not None:
            out += [f"{vdir.parent / 'map.json'}: {p}" for p in problems(ident.dump(), "map-identity")]
    return out


@pytest.fixture(autouse=True)
def _published_versions_conform_to_the_schemas(tmp_path_factory, tmp_path):
    """After every test: each map version it published (in its ``tmp_path`` or a module's temporary folders)
    conforms to mapformat/schemas (manifest, changelog, identity). Requesting ``tmp_path`` makes this check run
    before the test's folder is removed."""
    yield
    found = published_documents_problems(tmp_path_factory.getbasetemp())
    assert not found, "published documents break the map format's JSON Schemas:\n" + "\n".join(found[:20])


@pytest.fixture(scope="session")
def s3_env():
    """A real S3 API server (moto's server mode) on 127.0.0.1, started by the test session itself
    (``fixtures/s3server.py``); the standard AWS environment points at it for this process and its children."""
    from fixtures.s3server import s3_server

    with s3_server() as env, pytest.MonkeyPatch.context() as mp:  # the environment restored after the session
        mp.delenv("AWS_PROFILE", raising=False)
        for k, v in env.items():
            mp.setenv(k, v)
        yield env


@pytest.fixture
def s3_root(s3_env, request) -> str:
    """``s3://BUCKET/root`` in a new bucket of the test server."""
    import re
    import secrets

    from fixtures.s3server import make_bucket

    bucket = (re.sub(r"[^a-z0-9-]", "-", request.node.name.lower())[:40].strip("-") + "-" + secrets.token_hex(3))
    make_bucket(s3_env, bucket)
    return f"s3://{bucket}/root"
