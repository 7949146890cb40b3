"""The description of one scene the pipeline's dataset stage writes (``dataset.json``), typed.

Written by ``stages/dataset.py`` (one builder per scene kind) and read by every later stage
and by the report through :class:`DatasetSpec`: one record, so that a field is named in one
place. It is a ``dict`` (the JSON as written, so an unchanged scene keeps the same bytes and
cache keys) with typed read-only accessors; kind-specific fields are ``None`` where absent.
"""

from __future__ import annotations

from typing import Optional

FORMAT = "cobgs-dataset"
VERSION = 1


class DatasetSpec(dict):
    """``dataset.json`` of a scene (see the module docstring)."""

    # -- every kind -----------------------------------------------------------------------
    @property
    def scene(self) -> str:
        return self["scene"]

    @property
    def kind(self) -> str:
        """synthetic, images, nvos, lerf_mask, transforms, blender, llff or colmap."""
        return self["kind"]

    @property
    def protocol(self) -> str:
        """exact (GT masks of held-out views), nvos, lerf_mask, spin, or none."""
        return self.get("protocol", "none")

    @property
    def objects(self) -> list:
        return list(self.get("objects") or [])

    @property
    def views(self) -> list:
        return list(self.get("views") or [])

    @property
    def test_views(self) -> list:
        return list(self.get("test_views") or [])

    @property
    def has_poses(self) -> bool:
        return bool(self.get("has_poses"))

    @property
    def scene_type(self) -> str:
        """forward or 360 ("" in older specs)."""
        return self.get("scene_type") or ""

    @property
    def notes(self) -> list:
        """What the reader decided (dropped distortion, matched file names ...)."""
        return list(self.get("notes") or [])

    @property
    def reader(self) -> dict:
        """How later stages read the scene: format, path, downscale, background, distortion."""
        return dict(self.get("reader") or {})

    @property
    def images(self) -> Optional[dict]:
        """The folder SfM runs on: ``{"dir", "names"}``, or None (no single image folder)."""
        return self.get("images")

    @property
    def sfm_downscale(self) -> float:
        return float(self.get("sfm_downscale", 1.0))

    @property
    def source(self) -> Optional[str]:
        """The data folder (every kind but synthetic)."""
        return self.get("source")

    # -- kind-specific ----------------------------------------------------------------------
    @property
    def amodal(self) -> Optional[dict]:
        """Whole-silhouette GT of held-out views: ``{"source", "dir", "objects"}``."""
        return self.get("amodal")

    @property
    def nvos(self) -> Optional[dict]:
        """The NVOS task (the first, when the scene holds several)."""
        return self.get("nvos")

    @property
    def nvos_tasks(self) -> dict:
        """task -> its record, when the scene holds several NVOS tasks (horns)."""
        return dict(self.get("nvos_tasks") or {})

    @property
    def lerf_mask(self) -> Optional[dict]:
        return self.get("lerf_mask")

    @property
    def spin(self) -> Optional[dict]:
        """SPIn-NeRF's annotations (:meth:`cobgs.data.spin.SpinScene.to_json`): masks, prompt, scored."""
        return self.get("spin")

    def nvos_task(self, *names: str) -> Optional[dict]:
        """The NVOS task an object stands for: with several tasks, the entry of the first of
        ``names`` (the object's name, then its ``mask``) that is one of them; else the one
        task; None when none matches."""
        tasks = self.nvos_tasks
        if not tasks:
            return self.nvos
        for n in names:
            if n in tasks:
                return tasks[n]
        return None
