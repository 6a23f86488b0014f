"""LiDAR-free toy stages that exercise the engine: numbers -> squares (per chunk) -> total (single)."""
from __future__ import annotations

import os
import time

import numpy as np
import pyarrow as pa

from pipeline.declare import Params, Partitioning, StageDecl
from pipeline.errors import DataQualityError

NUMBERS = pa.schema([pa.field("drive", pa.string(), nullable=False), pa.field("chunk", pa.int32(), nullable=False),
                     pa.field("value", pa.float64(), nullable=False)])
SQUARES = NUMBERS
TOTAL = pa.schema([pa.field("total", pa.float64(), nullable=False), pa.field("n", pa.int64(), nullable=False)])


class NumbersParams(Params):
    n_chunks: int = 4
    per_chunk: int = 100
    seed: int = 0
    slow_drive: str = ""  # this drive's partition sleeps ``sleep_s`` (lets a test see stages overlap)
    sleep_s: float = 0.0


class SquaresParams(Params):
    offset: float = 0.0
    sleep_s: float = 0.0  # lets a test kill a run in the middle of this stage


class TotalParams(Params):
    scale: float = 1.0
    refuse: bool = False  # its quality gate refuses the sum (a DataQualityError: exit 3)
    sleep_s: float = 0.0  # lets a test stop a run in this single-partition stage (a thread of the run's process)


def numbers(ctx):
    p = ctx.params
    rng = np.random.default_rng(p.seed)
    if p.sleep_s and ctx.partition.drive == p.slow_drive:
        time.sleep(p.sleep_s)

    def pieces():
        for c in range(p.n_chunks):
            v = rng.normal(size=p.per_chunk)
            yield pa.table({"drive": [ctx.partition.drive] * p.per_chunk, "chunk": np.full(p.per_chunk, c, np.int32),
                            "value": v})
    return {"numbers": pieces(), "_extra": {"origin": "toy"}}


def squares(ctx):
    t = ctx.inputs.read("numbers", partition=ctx.partition)
    if ctx.params.sleep_s:
        time.sleep(ctx.params.sleep_s)
    v = t["value"].to_numpy() ** 2 + ctx.params.offset
    out = pa.table({"drive": t["drive"], "chunk": t["chunk"], "value": v})
    note = ctx.artifact_dir("notes") / "note.txt"
    threads = " ".join(f"{v}={os.environ.get(v)}" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"))
    note.write_text(f"{ctx.partition.label} pid={os.getpid()} {threads}\n")
    return {"squares": out, "notes": None}


def total(ctx):
    t = ctx.inputs.read("squares")
    for k in range(int(ctx.params.sleep_s)):
        ctx.report_step("waiting", k, int(ctx.params.sleep_s))
        time.sleep(1.0)
    if ctx.params.refuse:
        raise DataQualityError(f"toy total: the quality gate refused the sum of {t.num_rows} squares")
    return {"total": pa.table({"total": [float(np.sum(t["value"].to_numpy())) * ctx.params.scale],
                               "n": [t.num_rows]})}


NUMBERS_STAGE = StageDecl(name="numbers", summary="toy: random numbers per drive", code_version="1", inputs={},
                          outputs={"numbers": "toy_numbers"}, params=NumbersParams, partition=Partitioning.PER_DRIVE,
                          uses_drives=True, compute="tests.pipeline.toy_stages:numbers")
SQUARES_STAGE = StageDecl(name="squares", summary="toy: squares per chunk", code_version="1",
                          inputs={"numbers": "toy_numbers"}, outputs={"squares": "toy_squares", "notes": "toy_notes"},
                          params=SquaresParams, partition=Partitioning.PER_SCAN_CHUNK, partition_source="numbers",
                          compute="tests.pipeline.toy_stages:squares")
TOTAL_STAGE = StageDecl(name="total", summary="toy: sum", code_version="1", inputs={"squares": "toy_squares"},
                        outputs={"total": "toy_total"}, params=TotalParams, partition=Partitioning.SINGLE,
                        compute="tests.pipeline.toy_stages:total")
EXTRA = ",".join(f"tests.pipeline.toy_stages:{n}" for n in ("NUMBERS_STAGE", "SQUARES_STAGE", "TOTAL_STAGE"))
