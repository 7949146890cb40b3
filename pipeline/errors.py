"""Errors raised by the pipeline engine.

Every message names where the problem is (workflow file and key, stage, artifact, cache
entry) and what was expected. The engine never imports ``cobgs``; the command line maps
these to one-line messages.
"""

from __future__ import annotations

import difflib
from typing import Iterable, Optional


class PipelineError(Exception):
    """Base class of every error the engine raises on purpose."""


class StageSpecError(PipelineError, ValueError):
    """A :class:`~pipeline.stage.Stage` declaration is invalid."""


class GraphError(PipelineError):
    """The stages do not form a valid DAG."""


class CycleError(GraphError):
    """The stages depend on each other in a cycle; ``cycle`` lists the stage names."""

    def __init__(self, cycle: list[str]):
        self.cycle = list(cycle)
        super().__init__("stages form a cycle: " + " -> ".join(self.cycle))


class DuplicateOutputError(GraphError):
    """Two stages declare the same output artifact (or a stage is registered twice)."""


class MissingInputError(GraphError):
    """A stage needs an artifact that no stage produces."""


class WorkflowError(PipelineError, ValueError):
    """A workflow file (or a ``--set`` override) is invalid.

    Args:
        message: what is wrong and what was expected.
        source: the workflow file, or ``"--set"`` for command-line overrides.
        key: the dotted key at fault, e.g. ``params.train.iterations``.
    """

    def __init__(self, message: str, source: Optional[str] = None, key: Optional[str] = None):
        self.source, self.key = source, key
        where = ": ".join(s for s in (source, key) if s)
        super().__init__(f"{where}: {message}" if where else message)


class OutputError(PipelineError):
    """A stage returned outputs that do not match its declaration."""


class CacheError(PipelineError):
    """The cache folder is unusable (not writable, wrong layout)."""


class ExecutorError(PipelineError):
    """An executor cannot be used (e.g. Ray is not installed or cannot connect)."""


def unknown_key_hint(key: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` when a close match exists, plus the list of valid keys."""
    known = sorted(known)
    close = difflib.get_close_matches(key, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    valid = ", ".join(known) if known else "none"
    return f"{hint}; expected one of: {valid}"
