"""A stage's code_version digests its code and the shared code it imports (transitively): an edit of code it runs
changes it, an edit of prose or of code it does not run does not, so a committed output is never reused for other
code and per-drive work is reused while the code is the same."""
from __future__ import annotations

import re
import sys
import textwrap

import pytest

import pipeline.declare as declare
from pipeline.declare import source_digest


@pytest.fixture()
def toy_tree(tmp_path, monkeypatch):
    """toystage/ imports toyshared.a, which imports toyshared.b; toyshared.c is imported by nobody."""
    def write(rel: str, text: str) -> None:
        f = tmp_path / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(textwrap.dedent(text))

    write("toystage/__init__.py", "")
    write("toystage/compute.py", """\
        from toyshared.a import double

        def compute(x):
            return double(x) + 1
        """)
    write("toyshared/__init__.py", "")
    write("toyshared/a.py", """\
        from toyshared.b import scale

        def double(x):
            return scale(x, 2)
        """)
    write("toyshared/b.py", '''\
        """Scaling."""

        def scale(x, k):
            """Multiply."""
            return x * k  # plain product
        ''')
    write("toyshared/c.py", "def unused():\n    return 0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(declare, "_PARSED", {})
    yield tmp_path, write
    for name in [m for m in sys.modules if m.startswith(("toystage", "toyshared"))]:
        del sys.modules[name]


def digest(tmp_path) -> str:
    declare._PARSED.clear()  # a new process would parse the files again
    return source_digest("toystage", follow=("toyshared",))


def test_code_the_stage_runs_through_its_imports_changes_the_digest(toy_tree):
    tmp_path, write = toy_tree
    before = digest(tmp_path)
    assert set(declare._code_files(("toystage",), ("toyshared",))) == {
        "toystage.__init__", "toystage.compute", "toyshared.a", "toyshared.b"}
    write("toyshared/b.py", "def scale(x, k):\n    return x * k * 1.0\n")  # two imports away
    assert digest(tmp_path) != before


def test_prose_comments_and_code_it_does_not_run_leave_the_digest(toy_tree):
    tmp_path, write = toy_tree
    before = digest(tmp_path)
    write("toyshared/b.py", '''\
        """Scaling, reworded: a longer module docstring."""


        def scale(x, k):
            """Multiply x by k (reworded)."""
            # a new comment
            return x * k
        ''')
    write("toyshared/c.py", "def unused():\n    return 1\n")  # nobody imports it
    assert digest(tmp_path) == before


def test_a_missing_module_is_named():
    with pytest.raises(ImportError, match="no module 'stages.nonexistent'"):
        source_digest("stages.nonexistent")


def test_every_stage_declares_its_code_digest():
    from pipeline.registry import load_stages

    for decl in load_stages().values():
        assert re.fullmatch(r"\d+\+[0-9a-f]{12}", decl.code_version), (decl.name, decl.code_version)
