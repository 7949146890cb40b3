"""Every configuration of the library, by subject, in modules that import nothing heavy.

``from cobgs.configs import X`` is each config's one import path: the algorithm modules and
the pipeline's stages import them from here (the stages declare them as their params
directly), so ``cobgs --help`` and a fully cached ``cobgs run`` never import torch (or numpy)
to read a workflow, and every value is checked where it is set.

* :mod:`~cobgs.configs.checks`: ``check_params`` (each range stated once, as ``RANGES`` /
  ``CHOICES`` on its class; ``__post_init__`` keeps only the checks across fields) and the
  "added later" rule that keeps earlier cache keys (``key_without_later``);
* :mod:`~cobgs.configs.files`: ``Files``, the artifact catalog (every file and sub-folder a
  stage writes);
* :mod:`~cobgs.configs.data`: scenes, SfM, mask noise; :mod:`~cobgs.configs.train`: the
  baseline training and its recipes; :mod:`~cobgs.configs.refine`: COB-GS and the peers;
  :mod:`~cobgs.configs.masks`: the prompt routes.
"""

from .checks import check_params, in_interval, key_without_later, parse_interval, with_later_values
from .data import MATCHERS, DatasetConfig, MaskNoiseParams, SfmOptions
from .files import Files
from .masks import ScribbleConfig, TwoStageConfig
from .refine import (CHECKED, FOREGROUND_LABEL, LABEL, NOSPLIT_SWITCHES, RAEM_VARIANTS, SCENE_DEFAULTS, TEXTURE_ADAM,
                     FlashSplatConfig, LUDVIGConfig, NGSConfig, RefineConfig, SA3DConfig)
from .train import FAST_RECIPE, RECIPES, RECIPES_NAMES, Schedule, TrainConfig

__all__ = ["Files", "DatasetConfig", "NGSConfig", "NOSPLIT_SWITCHES", "key_without_later", "with_later_values",
           "check_params", "parse_interval", "in_interval", "TrainConfig", "Schedule", "RefineConfig", "SA3DConfig",
           "FlashSplatConfig", "LUDVIGConfig", "TwoStageConfig", "ScribbleConfig", "MaskNoiseParams", "SfmOptions", "LABEL",
           "RAEM_VARIANTS", "TEXTURE_ADAM", "SCENE_DEFAULTS", "MATCHERS", "RECIPES", "RECIPES_NAMES", "FAST_RECIPE",
           "FOREGROUND_LABEL", "CHECKED"]
