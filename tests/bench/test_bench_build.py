"""The build bench's CPU figure: user + system time of the whole process tree, reaped descendants included."""
from __future__ import annotations

import subprocess
import sys

BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < {s}:\n    pass\n"


def test_tree_cpu_counts_a_child_and_a_grandchild_after_they_exit():
    """A child that burns 0.4 s of CPU and waits for a grandchild that burns 0.4 s: both count once they are reaped
    (they were invisible to a sampler of live processes after they exited)."""
    from bench.bench_build import tree_cpu_s

    grandchild = BURN.format(s=0.4)
    child = (BURN.format(s=0.4) + "import subprocess, sys\n"
             f"subprocess.run([sys.executable, '-c', {grandchild!r}], check=True)\n")
    before = tree_cpu_s()
    subprocess.run([sys.executable, "-c", child], check=True)
    spent = tree_cpu_s() - before
    assert 0.8 <= spent < 3.0
