"""`cornermap evaluate` names a map as every command does: --root ROOT --map NAME [--map-version vNNNN]."""
from __future__ import annotations

import pytest

from pipeline.errors import OptionError, UnknownNameError
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


def test_a_path_is_refused_as_a_usage_error(root):
    """A map is named, never a path (every command does so): a path in --map is a usage error naming the way."""
    for path in (root / "maps" / "demo", root / "maps" / "demo" / "v0001"):
        with pytest.raises(OptionError, match="is a path; a map is named: --root ROOT --map NAME") as info:
            open_named_map(root, str(path), "LATEST")
        assert info.value.exit_code == 2


def test_help_examples_use_root_and_map_name():
    from stages.evaluate.cli import EXAMPLES

    lines = [ln for ln in EXAMPLES.splitlines() if ln.strip().startswith("cornermap evaluate")]
    assert len(lines) == 2 and all(" --root runs/" in ln and "--map " in ln for ln in lines)
    assert not any("/maps/" in ln for ln in lines)  # a map is named, never a path (tests/test_help_examples.py)
