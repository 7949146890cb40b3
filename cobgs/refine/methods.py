"""The refinement methods behind one small protocol: a new method is one class and one line
of :data:`REGISTRY` (docs/method.md §3 "Adding a method").

:class:`RefineMethod` is everything the pipeline and the report need of a method, in one
object: its ``name`` (``refine.method``), its ``label`` (the report's word for it), its
``config_class``, the params ``sections`` its config comes from (the refine stage's ``cobgs``
/ ``sa3d`` / ``flashsplat`` / ``ngs`` tables), how those become the config
(:meth:`~RefineMethod.config_of`), what of the stage's params enters its cache key
(:meth:`~RefineMethod.key_params`: its own sections and the scene type, never another
method's), whether it alternates COB-GS's stages (texture moments, the stage-length warning,
the schedule in refine.json), and :meth:`~RefineMethod.run` on a :class:`RefineInputs`. This
module imports nothing heavy: the stage's params and the report read it without torch;
:meth:`run` imports the algorithm when called.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional, Sequence

from cobgs.configs import (NOSPLIT_SWITCHES, FlashSplatConfig, LUDVIGConfig, NGSConfig, RefineConfig, SA3DConfig,
                           key_without_later)
from cobgs.errors import InputError


@dataclasses.dataclass(frozen=True)
class RefineInputs:
    """What every method refines, the same for all (the stage builds it once).

    Attributes:
        model: the trained scene (not modified).
        views: the training views; masks: the object's mask per view (None = no mask).
        extent: the scene extent.
        background: the baseline's background colour.
        object_name: recorded in the result.
        progress: False, True (a tqdm bar) or a factory (:mod:`cobgs.progress`).
        texture_moments: the baseline's Adam moments, where COB-GS's texture stages start;
            methods without texture stages ignore them.
    """

    model: Any
    views: Sequence
    masks: Sequence
    extent: float
    background: Sequence[float] = (0.0, 0.0, 0.0)
    object_name: str = ""
    progress: Any = True
    texture_moments: Any = None


class RefineMethod:
    """The protocol (module docstring); subclasses set the class attributes and ``_run``."""

    name: str = ""
    label: str = ""
    config_class: type = object
    sections: tuple[str, ...] = ()
    #: alternates COB-GS's MASK / TEXTURE stages (texture moments, the stage-length warning)
    alternates: bool = False
    #: the name of a stage this method adds to COB-GS's (whose ``cobgs`` section it also reads),
    #: or "": the report's Table 5 shows such a method as COB-GS's switches plus that stage
    extra_stage: str = ""
    #: the params every method reads beside its sections (the refine stage's own fields)
    COMMON = ("method", "scene_type")

    def config_of(self, params: Any, scene_type: str = "") -> Any:
        """The library config of this method from the refine stage's params (its sections)."""
        return getattr(params, self.sections[0])

    def key_params(self, params_json: Mapping[str, Any]) -> dict:
        """What of the refine stage's params (as JSON) enters this method's cache key: the
        method's name, the scene type and its own sections (:meth:`key_section`), nothing of
        another method's: tuning one peer never recomputes another."""
        out = {k: params_json[k] for k in self.COMMON if k in params_json}
        for sec in self.sections:
            out[sec] = self.key_section(sec, dict(params_json.get(sec) or {}))
        return out

    def key_section(self, section: str, values: dict) -> dict:
        """A section as it enters the key (hook: fields added later keep earlier keys)."""
        return values

    def schedule(self, config: Any) -> Optional[RefineConfig]:
        """The COB-GS config whose stages this method runs (refine.json's δ / plan), or None."""
        return None

    def run(self, inputs: RefineInputs, config: Any = None):
        """Refine ``inputs`` with ``config`` (None = this method's defaults), checked against
        :attr:`config_class`.

        Raises:
            InputError: a config of another class.
        """
        cfg = self.config_class() if config is None else config
        if not isinstance(cfg, self.config_class):
            raise InputError(f"method {self.name!r} takes a {self.config_class.__name__}, got {type(cfg).__name__}")
        return self._run(inputs, cfg)

    def _run(self, inputs: RefineInputs, config: Any):
        raise NotImplementedError


def _scene_typed(cfg: RefineConfig, params: Any, scene_type: str) -> RefineConfig:
    st = scene_type if getattr(params, "scene_type", "auto") == "auto" else params.scene_type
    return dataclasses.replace(cfg, scene_type=st or "forward")


def _cobgs_section(values: dict, forced: Optional[dict] = None) -> dict:
    """COB-GS's section in a key: fields added later left out while they hold their earlier
    value (:func:`cobgs.configs.key_without_later`: ``object_check`` "off", what every entry
    before the switch did), so that adding a switch keeps every earlier entry valid; and the
    check's own options left out while the check is off (``forced``: what the row imposes)."""
    return key_without_later(RefineConfig, values, forced)


class CobGS(RefineMethod):
    name, label, config_class, sections, alternates = "cobgs", "COB-GS", RefineConfig, ("cobgs",), True

    def config_of(self, params, scene_type=""):
        return _scene_typed(params.cobgs, params, scene_type)

    def key_section(self, section, values):
        return _cobgs_section(values)

    def schedule(self, config):
        return config

    def _run(self, inputs, config):
        from cobgs.refine.alternation import refine

        return refine(inputs.model, inputs.views, inputs.masks, inputs.extent, config, background=inputs.background,
                      object_name=inputs.object_name, progress=inputs.progress,
                      texture_moments=inputs.texture_moments)


class NoSplit(CobGS):
    """Label optimisation without splitting (paper Table 5, first row)."""

    name, label, alternates = "nosplit", "labels only, no split", False  # (mask stages only)

    def key_section(self, section, values):
        out = _cobgs_section(values, NOSPLIT_SWITCHES)
        # the switches this row forces off that were added later (NOSPLIT_SWITCHES; "before" in
        # their metadata) say nothing of it: out of its key whatever the params say
        for f in dataclasses.fields(RefineConfig):
            if f.name in NOSPLIT_SWITCHES and "before" in f.metadata:
                out.pop(f.name, None)
        return out

    def schedule(self, config):
        from cobgs.refine.peers import nosplit_config

        return nosplit_config(config)

    def _run(self, inputs, config):
        from cobgs.refine.peers import run_nosplit

        return run_nosplit(inputs.model, inputs.views, inputs.masks, inputs.extent, config,
                           background=inputs.background, object_name=inputs.object_name, progress=inputs.progress)


class SA3D(RefineMethod):
    name, label, config_class, sections = "sa3d", "SA3D-GS", SA3DConfig, ("sa3d",)

    def _run(self, inputs, config):
        from cobgs.refine.peers import run_sa3d

        return run_sa3d(inputs.model, inputs.views, inputs.masks, config, object_name=inputs.object_name,
                        progress=inputs.progress)


class FlashSplat(RefineMethod):
    name, label, config_class, sections = "flashsplat", "FlashSplat", FlashSplatConfig, ("flashsplat",)

    def _run(self, inputs, config):
        from cobgs.refine.peers import run_flashsplat

        return run_flashsplat(inputs.model, inputs.views, inputs.masks, config, object_name=inputs.object_name,
                              progress=inputs.progress)


class LUDVIG(RefineMethod):
    """LUDVIG: the masks uplifted by weighted back-projection, evaluated as its release
    evaluates (:mod:`cobgs.refine.ludvig`)."""

    name, label, config_class, sections = "ludvig", "LUDVIG", LUDVIGConfig, ("ludvig",)

    def _run(self, inputs, config):
        from cobgs.refine.ludvig import run_ludvig

        return run_ludvig(inputs.model, inputs.views, inputs.masks, config, object_name=inputs.object_name,
                          progress=inputs.progress)


@dataclasses.dataclass(frozen=True)
class NGSRun:
    """NG-GS's config: COB-GS's (the ``cobgs`` section) and its boundary stage's."""

    cobgs: RefineConfig = dataclasses.field(default_factory=RefineConfig)
    ngs: NGSConfig = dataclasses.field(default_factory=NGSConfig)


class NGS(CobGS):
    """NG-GS: COB-GS's stages plus the NeRF-guided boundary loss in the TEXTURE stages
    (:mod:`cobgs.refine.ngs`)."""

    name, label, config_class, sections, extra_stage = "ngs", "NG-GS", NGSRun, ("cobgs", "ngs"), "NG-GS"

    def config_of(self, params, scene_type=""):
        return NGSRun(_scene_typed(params.cobgs, params, scene_type), params.ngs)

    def key_section(self, section, values):
        return _cobgs_section(values) if section == "cobgs" else values

    def schedule(self, config):
        return config.cobgs

    def _run(self, inputs, config):
        from cobgs.refine.alternation import refine

        return refine(inputs.model, inputs.views, inputs.masks, inputs.extent, config.cobgs,
                      background=inputs.background, object_name=inputs.object_name, method="ngs",
                      progress=inputs.progress, texture_moments=inputs.texture_moments, ngs=config.ngs)


#: Every method, by name (``refine.method``).
REGISTRY: dict[str, RefineMethod] = {m.name: m for m in (CobGS(), NoSplit(), SA3D(), FlashSplat(), NGS(), LUDVIG())}
METHODS = tuple(REGISTRY)
#: Every params section some method reads (the refine stage's params are exactly these plus
#: :attr:`RefineMethod.COMMON`).
SECTIONS = tuple(dict.fromkeys(sec for m in REGISTRY.values() for sec in m.sections))


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
    cls = method_for(method).config_class
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
    """Run one segmentation method on one object: ``method_for(method).run(RefineInputs(...),
    config)`` (:data:`cobgs.refine.methods.REGISTRY`).

    Args:
        method: "cobgs" (config: :class:`RefineConfig`, ablations included), "nosplit"
            (:class:`RefineConfig`, switches forced off), "sa3d" (:class:`SA3DConfig`),
            "flashsplat" (:class:`FlashSplatConfig`) or "ngs"
            (:class:`cobgs.refine.methods.NGSRun`).
        config: the method's config (None = its defaults).
        the rest: :class:`RefineInputs`.
    """
    inputs = RefineInputs(model, views, masks, extent, background=background, object_name=object_name,
                          progress=progress, texture_moments=texture_moments)
    return method_for(method).run(inputs, config)


__all__ = ["METHODS", "NGSRun", "REGISTRY", "RefineInputs", "RefineMethod", "SECTIONS", "make_config", "method_for",
           "run_method"]
