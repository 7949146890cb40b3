"""A generic, cached, staged DAG engine. It knows nothing of Gaussians or images.

The model (docs/pipeline.md has the long version):

* A :class:`Stage` declares a name, a version, named input and output artifacts, a frozen
  params dataclass, the *level* it runs at (workflow axes such as ``("scene",)`` or
  ``("scene", "method")``; ``()`` = once per workflow) and ``run(ctx, inputs) -> outputs``.
* A :class:`Registry` holds a program's stages; the DAG comes from matching artifact
  names (:class:`Graph`).
* A workflow TOML file (:func:`load_workflow`) declares the axes and their values (the
  items), per-stage params, per-item overrides and settings such as ``device``.
* A run (:func:`run_workflow`) expands the workflow into tasks (stage x item), computes
  each task's cache key from its stage, version, params, item and upstream output hashes,
  reuses finished entries and executes the rest (in process, in forked workers, or on Ray).
* :func:`entries` reads the state of every task back for reports and exports.
"""

from .api import entries, entry_of, load_manifest, upstream_entries
from .cache import Cache
from .context import StageContext
from .errors import (
    CacheError,
    CycleError,
    DuplicateOutputError,
    ExecutorError,
    GraphError,
    MissingInputError,
    PipelineError,
    StageSpecError,
    WorkflowError,
)
from .graph import Graph
from .items import Item
from .plan import Plan, TaskState, inspect
from .registry import Registry
from .run import RunOptions, RunSummary, run_workflow
from .stage import NoParams, Resources, Stage
from .values import Settings
from .workflow import Workflow, load_workflow

__all__ = [
    "Cache", "CacheError", "CycleError", "DuplicateOutputError", "ExecutorError", "Graph",
    "GraphError", "Item", "MissingInputError", "NoParams", "PipelineError", "Plan",
    "Registry", "Resources", "RunOptions", "RunSummary", "Settings", "Stage", "StageContext",
    "StageSpecError", "TaskState", "Workflow", "WorkflowError", "entries", "inspect",
    "entry_of", "load_manifest", "load_workflow", "run_workflow", "upstream_entries",
]
