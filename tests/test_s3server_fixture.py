"""The local S3 server the README tells users to start: a bucket name S3 would refuse is refused up front, as a
usage error with one line, not a traceback from the client."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from fixtures.s3server import bucket_name

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["maps", "hc-maps", "city.maps.2026", "a1b"])
def test_bucket_names_s3_accepts(name: str) -> None:
    assert bucket_name(name) == name


@pytest.mark.parametrize("name", ["ab", "Maps", "maps_1", "-maps", "maps-", "a..b", "192.168.1.2", "x" * 64])
def test_bucket_names_s3_refuses(name: str) -> None:
    with pytest.raises(ValueError, match="is no S3 bucket name"):
        bucket_name(name)


def test_the_server_command_refuses_a_bad_bucket_with_exit_2_and_one_line() -> None:
    res = subprocess.run([sys.executable, "-m", "fixtures.s3server", "--bucket", "ab"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "'ab' is no S3 bucket name" in res.stderr and "Traceback" not in res.stderr
