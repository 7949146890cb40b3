"""The refinement methods behind one small protocol: a new method is one class and one line
of :data:`REGISTRY` (docs/method.md §3 "Adding a method").

:class:`RefineMethod` says what the pipeline and the report need of a method: its ``name``
(``refine.method``), its ``label`` (the report's word for it), the params ``sections`` its
config comes from (the refine stage's ``cobgs`` / ``sa3d`` / ``flashsplat`` / ``ngs`` tables),
how those become the library config (:meth:`~RefineMethod.config_of`), whether it alternates
COB-GS's stages (texture moments, the stage-length warning, the schedule in refine.json), and
:meth:`~RefineMethod.run`. This module imports nothing heavy: the stage's params and the
report read it without torch; :meth:`run` imports the algorithm when called.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional, Sequence

from cobgs.configs import FlashSplatConfig, NGSConfig, RefineConfig, SA3DConfig
from cobgs.errors import InputError


class RefineMethod:
    """The protocol (module docstring); subclasses set the class attributes and ``run``."""

    name: str = ""
    label: str = ""
    sections: tuple[str, ...] = ()
    #: alternates COB-GS's MASK / TEXTURE stages (texture moments, the stage-length warning)
    alternates: bool = False
    #: the name of a stage this method adds to COB-GS's (whose ``cobgs`` section it also reads),
    #: or "": the report's Table 5 shows such a method as COB-GS's switches plus that stage
    extra_stage: str = ""

    def config_of(self, params: Any, scene_type: str = "") -> Any:
        """The library config of this method from the refine stage's params (its sections)."""
        return getattr(params, self.sections[0])

    def schedule(self, config: Any) -> Optional[RefineConfig]:
        """The COB-GS config whose stages this method runs (refine.json's δ / plan), or None."""
        return None

    def run(self, model, views: Sequence, masks: Sequence, extent: float, config: Any, *,
            background=(0.0, 0.0, 0.0), object_name: str = "", progress=True, texture_moments=None):
        raise NotImplementedError


def _scene_typed(cfg: RefineConfig, params: Any, scene_type: str) -> RefineConfig:
    st = scene_type if getattr(params, "scene_type", "auto") == "auto" else params.scene_type
    return dataclasses.replace(cfg, scene_type=st or "forward")


class CobGS(RefineMethod):
    name, label, sections, alternates = "cobgs", "COB-GS", ("cobgs",), True

    def config_of(self, params, scene_type=""):
        return _scene_typed(params.cobgs, params, scene_type)

    def schedule(self, config):
        return config

    def run(self, model, views, masks, extent, config, *, background=(0.0, 0.0, 0.0), object_name="",
            progress=True, texture_moments=None):
        from cobgs.refine.alternation import refine

        return refine(model, views, masks, extent, config, background=background, object_name=object_name,
                      progress=progress, texture_moments=texture_moments)


class NoSplit(CobGS):
    """Label optimisation without splitting (paper Table 5, first row)."""

    name, label, alternates = "nosplit", "labels only, no split", False  # (mask stages only)

    def schedule(self, config):
        from cobgs.refine.peers import nosplit_config

        return nosplit_config(config)

    def run(self, model, views, masks, extent, config, *, background=(0.0, 0.0, 0.0), object_name="",
            progress=True, texture_moments=None):
        from cobgs.refine.peers import run_nosplit

        return run_nosplit(model, views, masks, extent, config, background=background, object_name=object_name,
                           progress=progress)


class SA3D(RefineMethod):
    name, label, sections = "sa3d", "SA3D-GS", ("sa3d",)

    def run(self, model, views, masks, extent, config, *, background=(0.0, 0.0, 0.0), object_name="",
            progress=True, texture_moments=None):
        from cobgs.refine.peers import run_sa3d

        return run_sa3d(model, views, masks, config, object_name=object_name, progress=progress)


class FlashSplat(RefineMethod):
    name, label, sections = "flashsplat", "FlashSplat", ("flashsplat",)

    def run(self, model, views, masks, extent, config, *, background=(0.0, 0.0, 0.0), object_name="",
            progress=True, texture_moments=None):
        from cobgs.refine.peers import run_flashsplat

        return run_flashsplat(model, views, masks, config, object_name=object_name, progress=progress)


@dataclasses.dataclass(frozen=True)
class NGSRun:
    """NG-GS's config: COB-GS's (the ``cobgs`` section) and its boundary stage's."""

    cobgs: RefineConfig = dataclasses.field(default_factory=RefineConfig)
    ngs: NGSConfig = dataclasses.field(default_factory=NGSConfig)


class NGS(CobGS):
    """NG-GS: COB-GS's stages plus the NeRF-guided boundary loss in the TEXTURE stages
    (:mod:`cobgs.refine.ngs`)."""

    name, label, sections, extra_stage = "ngs", "NG-GS", ("cobgs", "ngs"), "NG-GS"

    def config_of(self, params, scene_type=""):
        return NGSRun(_scene_typed(params.cobgs, params, scene_type), params.ngs)

    def schedule(self, config):
        return config.cobgs

    def run(self, model, views, masks, extent, config, *, background=(0.0, 0.0, 0.0), object_name="",
            progress=True, texture_moments=None):
        from cobgs.refine.alternation import refine

        return refine(model, views, masks, extent, config.cobgs, background=background, object_name=object_name,
                      method="ngs", progress=progress, texture_moments=texture_moments, ngs=config.ngs)


#: Every method, by name (``refine.method``).
REGISTRY: dict[str, RefineMethod] = {m.name: m for m in (CobGS(), NoSplit(), SA3D(), FlashSplat(), NGS())}
METHODS = tuple(REGISTRY)
#: The config class :func:`method_for` checks a config against, per method.
CONFIG_CLASSES = {"cobgs": RefineConfig, "nosplit": RefineConfig, "sa3d": SA3DConfig, "flashsplat": FlashSplatConfig,
                  "ngs": NGSRun}


def method_for(name: str) -> RefineMethod:
    """The method called ``name``.

    Raises:
        InputError: no such method (the known ones named).
    """
    if name not in REGISTRY:
        raise InputError(f"unknown method {name!r} (expected one of {list(METHODS)})")
    return REGISTRY[name]


def make_config(method: str, params: Optional[Mapping] = None):
    """The config dataclass of ``method`` from plain parameters (e.g. a workflow's TOML).

    Args:
        method: one of :data:`cobgs.refine.methods.METHODS`.
        params: field name → value; unknown names raise :class:`InputError`.
    """
    method_for(method)
    cls = CONFIG_CLASSES[method]
    params = dict(params or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(params) - names)
    if unknown:
        raise InputError(f"unknown {cls.__name__} parameter(s) {unknown} for method {method!r}; "
                         f"expected some of {sorted(names)}")
    return cls(**params)


def run_method(
    method: str,
    model,
    views: Sequence,
    masks: Sequence,
    extent: float,
    *,
    config=None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    object_name: str = "",
    progress=True,
    texture_moments=None,
):
    """Run one segmentation method on one object (:data:`cobgs.refine.methods.REGISTRY`).

    Args:
        method: "cobgs" (config: :class:`RefineConfig`, ablations included), "nosplit"
            (:class:`RefineConfig`, switches forced off), "sa3d" (:class:`SA3DConfig`),
            "flashsplat" (:class:`FlashSplatConfig`) or "ngs"
            (:class:`cobgs.refine.methods.NGSRun`).
        model: the trained scene (not modified).
        views, masks, extent, background: as in :func:`cobgs.refine.alternation.refine`.
        config: the method's config (None = its defaults).
        object_name: recorded in the result.
        progress: False, True (a tqdm bar) or a factory (:mod:`cobgs.progress`).
        texture_moments: the baseline's Adam moments, where COB-GS's texture stages start
            (:func:`cobgs.refine.alternation.refine`); methods without texture stages ignore them.
    """
    spec = method_for(method)
    cls = CONFIG_CLASSES[method]
    cfg = cls() if config is None else config
    if not isinstance(cfg, cls):
        raise InputError(f"method {method!r} takes a {cls.__name__}, got {type(cfg).__name__}")
    return spec.run(model, views, masks, extent, cfg, background=background, object_name=object_name,
                    progress=progress, texture_moments=texture_moments)


__all__ = ["CONFIG_CLASSES", "METHODS", "NGSRun", "REGISTRY", "RefineMethod", "make_config", "method_for", "run_method"]
