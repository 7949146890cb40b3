"""Toy stages for the engine's tests: the shape of the real DAG, none of its content.

    load (per scene) -> train (per scene, uses the device) -> refine (scene x method)
        -> evaluate (scene x method) -> summary (once: fan-in over every item)

Every execution appends ``<stage> <item id>`` to the file named by ``$PIPELINE_TOYS_LOG``
(when set), so tests can count what actually ran, across processes. Behaviour that must
not change cache keys comes from the environment too: ``$PIPELINE_TOYS_SLEEP`` (seconds
every stage sleeps) and ``$PIPELINE_TOYS_HANG`` (a marker path: while the file
``<marker>.arm`` exists, refine writes half its output, writes its pid to the marker, then
sleeps in short steps, for kill and interrupt tests; limited to the item
``$PIPELINE_TOYS_HANG_ITEM`` when set).
Importable as ``pipeline_toys`` (tests/pipeline on sys.path), also by subprocesses and Ray
workers given ``PYTHONPATH``; ``COBGS_STAGE_MODULES=pipeline_toys`` plugs these stages into
the ``cobgs`` command.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Optional

from pipeline import Registry, Resources, Stage


def record(stage: str, ctx: Any) -> None:
    log = os.environ.get("PIPELINE_TOYS_LOG")
    if log:
        with open(log, "a") as f:
            f.write(f"{stage} {ctx.item.id}\n")
    time.sleep(float(os.environ.get("PIPELINE_TOYS_SLEEP", "0")))


@dataclass(frozen=True)
class LoadParams:
    size: int = 3
    source: Optional[Path] = None


def run_load(ctx, inputs):
    record("load", ctx)
    out = ctx.out_dir / "data.txt"
    attrs = ctx.item.attrs["scene"]
    out.write_text(f"scene={ctx.item['scene']} kind={attrs.get('kind')} size={ctx.params.size}\n")
    return {"data": out}


@dataclass(frozen=True)
class TrainParams:
    iterations: int = 10
    fail_on: str = ""  # scene name whose training raises
    disk_full_on: str = ""  # scene name whose training fails with "No space left on device"


def run_train(ctx, inputs):
    record("train", ctx)
    if ctx.params.fail_on and ctx.item["scene"] == ctx.params.fail_on:
        raise RuntimeError(f"toy training diverged on {ctx.item['scene']}")
    if ctx.params.disk_full_on and ctx.item["scene"] == ctx.params.disk_full_on:
        import errno

        raise OSError(errno.ENOSPC, "No space left on device", str(ctx.out_dir / "model"))
    data = Path(inputs["data"]).read_text()
    folder = ctx.out_dir / "model"
    folder.mkdir()
    (folder / "weights.txt").write_text(f"{data}iterations={ctx.params.iterations} "
                                        f"device={ctx.device}\n")
    (folder / "sub").mkdir()
    (folder / "sub" / "extra.bin").write_bytes(bytes(range(256)) * 4)
    ctx.log.info("trained %s", ctx.item.id)
    ctx.note(iterations_done=ctx.params.iterations)
    return {"model": folder}


@dataclass(frozen=True)
class RefineParams:
    strength: float = 1.0
    split: bool = True
    sleep_s: float = 0.0


def run_refine(ctx, inputs):
    record("refine", ctx)
    weights = (Path(inputs["model"]) / "weights.txt").read_text()
    out = ctx.out_dir / "refined.txt"
    p = ctx.params
    marker = os.environ.get("PIPELINE_TOYS_HANG")
    if marker and os.path.exists(marker + ".arm") and \
            os.environ.get("PIPELINE_TOYS_HANG_ITEM", ctx.item.id) == ctx.item.id:
        with open(out, "w") as f:
            f.write("partial")
            f.flush()
            Path(marker).write_text(str(os.getpid()))
            for _ in range(3000):  # short steps: Ray's cancel lands between bytecodes
                time.sleep(0.1)
    for _ in ctx.progress(range(3), desc="refining"):
        time.sleep(p.sleep_s / 3)
    out.write_text(f"{weights}method={ctx.item['method']} strength={p.strength} split={p.split}\n")
    return {"refined": out}


@dataclass(frozen=True)
class EvaluateParams:
    threshold: float = 0.5


def run_evaluate(ctx, inputs):
    record("evaluate", ctx)
    text = Path(inputs["refined"]).read_text()
    out = ctx.out_dir / "metrics.json"
    out.write_text(json.dumps({"item": ctx.item.id, "chars": len(text),
                               "threshold": ctx.params.threshold}))
    return {"metrics": out}


@dataclass(frozen=True)
class SummaryParams:
    title: str = "toy"


def run_summary(ctx, inputs):
    record("summary", ctx)
    rows = {item.id: json.loads(Path(path).read_text()) for item, path in inputs["metrics"].items()}
    out = ctx.out_dir / "summary.json"
    out.write_text(json.dumps({"title": ctx.params.title, "rows": rows,
                               "items": [i.id for i in ctx.items]}, sort_keys=True))
    return {"summary": out}


LOAD = Stage(name="load", version=1, run=run_load, outputs=("data",), params=LoadParams,
             level=("scene",))
TRAIN = Stage(name="train", version=1, run=run_train, inputs=("data",), outputs=("model",),
              params=TrainParams, level=("scene",), uses_device=True)
REFINE = Stage(name="refine", version=1, run=run_refine, inputs=("model",),
               outputs=("refined",), params=RefineParams, level=("scene", "method"),
               uses_device=True, resources=Resources(cpus=1, gpus=1))
EVALUATE = Stage(name="evaluate", version=1, run=run_evaluate, inputs=("refined",),
                 outputs=("metrics",), params=EvaluateParams, level=("scene", "method"))
SUMMARY = Stage(name="summary", version=1, run=run_summary, inputs=("metrics",),
                outputs=("summary",), params=SummaryParams, level=())

STAGES = (LOAD, TRAIN, REFINE, EVALUATE, SUMMARY)


def registry(**versions: Any) -> Registry:
    """The toy registry; ``registry(refine=2)`` bumps a stage's version."""
    return Registry([replace(s, version=versions.get(s.name, s.version)) for s in STAGES])


WORKFLOW = """\
[workflow]
name = "toy"

[settings]
device = "cpu"

[params.train]
iterations = 10

[axes.scene.alpha]
kind = "synthetic"

[axes.scene.beta]
kind = "synthetic"
train = { iterations = 20 }

[axes.method.full]

[axes.method.nosplit]
refine = { split = false }
"""


def write_workflow(folder: Path, text: str = WORKFLOW, name: str = "toy.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path
