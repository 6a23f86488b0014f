"""A URI given as ``--root`` or ``--inbox`` is never taken for a relative folder: a command that does not read object
storage refuses it with one usage line naming the option (exit 2) and writes nothing; run as a process from a folder
outside the checkout (issue 58: ``--root s3://maps/city-root`` used to write the folder ``s3:/maps/city-root``)."""
from __future__ import annotations

import pytest

from fixtures.cli import one_error_line
from tests.test_cli_process import cornermap

REFUSED = [
    (("build", "--drive", "d.yaml", "--map", "city", "--root", "gs://maps/city-root"), "--root"),  # s3:// builds
    (("run", "tiny", "--root", "gs://maps/city-root"), "--root"),
    (("corners", "run", "--workflow", "tiny", "--root", "s3://maps/city-root"), "--root"),
    (("gc", "--root", "gs://maps/city-root"), "--root"),  # gc reads s3:// roots, not others
    (("maps", "create", "--root", "gs://maps/city-root", "--map", "city", "--origin", "37.5,127.0,57"), "--root"),
    (("rebuild", "--root", "gs://maps/city-root", "--map", "city", "--inbox", "in"), "--root"),  # s3:// rebuilds
    (("rebuild", "--root", "local", "--map", "city", "--inbox", "gs://maps/inbox"), "--inbox"),
    (("tiles", "bundle", "--from", "v1", "--to", "v2", "--out", "o", "--root", "s3://maps/r", "--map", "c"), "--root"),
    (("tiles", "ls", "--root", "gs://maps/city-root"), "--root"),  # a scheme no command supports
]


@pytest.mark.parametrize("args,option", REFUSED, ids=[" ".join(a[:2]) + " " + o for a, o in REFUSED])
def test_a_uri_where_a_folder_is_expected_is_a_usage_error_naming_the_option(tmp_path, args, option):
    res = cornermap(*args, cwd=tmp_path)
    line = one_error_line(res)
    assert res.returncode == 2, (args, res.returncode, res.stderr)
    assert line.startswith(f"error: {option}: ") and "://" in line and "URI" in line, line
    assert "Traceback" not in res.stderr
    assert list(tmp_path.iterdir()) == [], "a refused command wrote something"  # no s3:/maps/city-root folder


def test_the_environment_root_is_checked_like_the_option(tmp_path):
    res = cornermap("maps", "create", "--map", "city", "--origin", "37.5,127.0,57", cwd=tmp_path,
                    CORNERMAP_ROOT="gs://maps/city-root")
    assert res.returncode == 2 and one_error_line(res).startswith("error: --root: "), res.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_workflow_whose_root_is_a_uri_is_refused(tmp_path):
    import re

    from tests.test_cli_process import REPO

    text = (REPO / "workflows" / "tiny.yaml").read_text()
    text = re.sub(r"(?m)^name: tiny$", "name: tiny\nroot: s3://maps/r", text, count=1)
    (tmp_path / "wf.yaml").write_text(text)
    res = cornermap("run", str(tmp_path / "wf.yaml"), "--dry-run", cwd=tmp_path)
    assert res.returncode in (1, 2) and "URI" in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wf.yaml"]


def test_an_object_store_that_cannot_be_reached_is_one_line_not_a_bug(tmp_path):
    """An S3 root whose endpoint refuses the connection (no server on the port): exit 1, one line naming the endpoint
    and what to check; before, ``error: internal error EndpointConnectionError ... (a bug; ...)``."""
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"http://127.0.0.1:{port}"
    env = {"AWS_ENDPOINT_URL": endpoint, "AWS_ACCESS_KEY_ID": "x", "AWS_SECRET_ACCESS_KEY": "x",
           "AWS_DEFAULT_REGION": "us-east-1", "AWS_MAX_ATTEMPTS": "1"}
    res = cornermap("tiles", "ls", "--root", "s3://maps/city-root", "--map", "city", cwd=tmp_path, **env)
    assert res.returncode == 1, res.stderr
    line = one_error_line(res)
    assert endpoint in line and "AWS_ENDPOINT_URL" in line and "a bug" not in line, line
