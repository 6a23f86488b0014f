"""`cornermap evaluate` names a map as every command does: --root ROOT --map NAME [--version]; a path alone."""
from __future__ import annotations

import pytest

from pipeline.errors import ConfigError, UnknownNameError
from stages.evaluate.cli import open_named_map


@pytest.fixture()
def root(tmp_path):
    for name in ("gangnam", "demo"):
        (tmp_path / "maps" / name / "v0001").mkdir(parents=True)
        (tmp_path / "maps" / name / "LATEST").write_text("v0001\n")
        (tmp_path / "maps" / name / "v0001" / "manifest.json").write_text("{}")
    return tmp_path


def test_unknown_name_lists_the_maps_and_suggests(root):
    with pytest.raises(UnknownNameError, match=r"no map 'gangam'; have demo, gangnam \(did you mean 'gangnam'\?\)"):
        open_named_map(root, "gangam", "LATEST")


def test_no_name_needs_a_single_map(root, tmp_path_factory):
    with pytest.raises(UnknownNameError, match="several maps: demo, gangnam; hint: pass --root ROOT --map NAME"):
        open_named_map(root, None, "LATEST")
    with pytest.raises(UnknownNameError, match="no maps"):
        open_named_map(tmp_path_factory.mktemp("empty"), None, "LATEST")


def test_a_path_is_accepted_only_when_unambiguous(root):
    with pytest.raises(ConfigError, match="is a path and --root"):
        open_named_map(root, str(root / "maps" / "demo"), "LATEST")
    with pytest.raises(ConfigError, match="is the version folder v0001 and --version v0002 was given"):
        open_named_map(None, str(root / "maps" / "demo" / "v0001"), "v0002")
    with pytest.raises(ConfigError, match="not a published map folder"):
        open_named_map(None, str(root / "maps"), "LATEST")


def test_help_examples_use_root_and_map_name():
    from stages.evaluate.cli import EXAMPLES

    lines = [ln for ln in EXAMPLES.splitlines() if ln.strip().startswith("cornermap evaluate")]
    assert len(lines) == 2 and all(" --root runs/" in ln and "--map " in ln for ln in lines)
    assert not any("/maps/" in ln for ln in lines)  # a map is named, never a path (tests/test_help_examples.py)
