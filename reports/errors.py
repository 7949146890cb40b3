"""Errors of the report builder: one clear line naming the workflow, entry or file at fault."""

from __future__ import annotations

from cobgs.errors import CobgsError


class ReportError(CobgsError):
    """The report cannot be built (unreadable artifact, unwritable output folder, ...)."""
