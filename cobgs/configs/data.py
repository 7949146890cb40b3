"""Configs of the scene readers, SfM and the mask-noise generator (cobgs.data)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import ClassVar, Optional, Tuple

from cobgs.errors import InputError

from .checks import check_params

MATCHERS = ("auto", "exhaustive", "sequential")


# -- scenes (cobgs.data.build) ----------------------------------------------------------------------
@dataclass(frozen=True)
class DatasetConfig:
    """How a scene is generated or ingested (the dataset stage's params; cobgs.data.build).

    Attributes:
        preset: synthetic preset ("demo", "forward", "orbit").
        seed: synthetic seed.
        width_px, height_px, num_views, supersampling: synthetic overrides (0 = preset's).
        workers: processes rendering synthetic views (the output does not depend on it).
        downscale: divide the image size for training (LLFF: picks ``images_<k>/``).
        images_dir: image sub-folder SfM runs on ("" = ``images_<downscale>/`` when it
            exists, else ``images/``); when given, ``downscale`` applies after SfM.
        view_stride: keep every k-th view (sorted by name) — subsets of long captures.
        max_views: keep at most this many views after the stride (0 = all).
        test_every: hold out every k-th kept view when the data defines no split.
        background: RGB in [0, 1] that RGBA images are composited on (None: the reader's).
    """

    preset: str = "demo"
    seed: int = 0
    width_px: int = 0
    height_px: int = 0
    num_views: int = 0
    supersampling: int = 0
    workers: int = 1
    downscale: float = 1.0
    images_dir: str = ""
    view_stride: int = 1
    max_views: int = 0
    test_every: int = 8
    background: Optional[tuple[float, float, float]] = None

    RANGES: ClassVar[dict] = {
        "seed": "[0, 2147483647]", "width_px": "[0, 16384]", "height_px": "[0, 16384]", "num_views": "[0, 10000]",
        "supersampling": "[0, 16]", "workers": "[0, 256]", "downscale": "(0, 64]", "view_stride": "[1, 1e6]",
        "max_views": "[0, 1e6]", "test_every": "[0, 1e6]", "background": "[0, 1]"}

    def __post_init__(self) -> None:
        check_params(self)
        if self.test_every == 1:  # (a value the range holds, but not a split)
            raise ValueError("test_every = 1 holds out every view, leaving nothing to train on: 0 holds out "
                             "none, k >= 2 every k-th view")



# -- mask noise (cobgs.data.mask_noise) ---------------------------------------------------
@dataclass(frozen=True)
class MaskNoiseParams:
    """How often and how strongly masks are corrupted. Rates are probabilities per mask
    (one object in one view).

    Attributes:
        drop_rate: the mask is replaced by an empty one (then nothing else applies).
        morph_rate: the mask is eroded or dilated.
        morph_max_px: the erosion/dilation radius is uniform in 1..morph_max_px pixels.
        dilate_fraction: share of dilations among erosions/dilations.
        jitter_rate: the boundary is jittered.
        jitter_amplitude_px: the largest boundary displacement.
        jitter_scale_px: correlation length of the displacement along the boundary.
        blob_rate: spurious blobs are added.
        blob_count_max: blobs per affected mask, uniform in 1..blob_count_max.
        blob_radius_min_px, blob_radius_max_px: blob disc radius range.
        seed: base seed of every mask's random stream.
    """

    drop_rate: float = 0.05
    morph_rate: float = 0.3
    morph_max_px: int = 3
    dilate_fraction: float = 0.5
    jitter_rate: float = 0.3
    jitter_amplitude_px: float = 2.0
    jitter_scale_px: float = 6.0
    blob_rate: float = 0.2
    blob_count_max: int = 3
    blob_radius_min_px: int = 2
    blob_radius_max_px: int = 5
    seed: int = 0

    RANGES: ClassVar[dict] = {
        "drop_rate": "[0, 1]", "morph_rate": "[0, 1]", "morph_max_px": "[1, 1000]", "dilate_fraction": "[0, 1]",
        "jitter_rate": "[0, 1]", "jitter_amplitude_px": "(0, 1000]", "jitter_scale_px": "(0, 1000]",
        "blob_rate": "[0, 1]", "blob_count_max": "[1, 1000]", "blob_radius_min_px": "[1, 1000]",
        "blob_radius_max_px": "[1, 1000]", "seed": "[0, 2147483647]"}

    def __post_init__(self) -> None:
        check_params(self)
        if self.blob_radius_max_px < self.blob_radius_min_px:
            raise InputError("MaskNoiseParams.blob_radius_max_px must be >= blob_radius_min_px, "
                             f"got {self.blob_radius_max_px} < {self.blob_radius_min_px}")



# -- SfM (cobgs.data.sfm) -----------------------------------------------------------------------
@dataclass(frozen=True)
class SfmOptions:
    """Options of :func:`run_sfm`.

    Attributes:
        matcher: "exhaustive" (every pair), "sequential" (each image with the next
            ``sequential_overlap`` in name order; for ordered captures) or "auto"
            (exhaustive up to ``exhaustive_max_images`` images, sequential above).
        exhaustive_max_images: the "auto" threshold.
        sequential_overlap: neighbours matched per image by the sequential matcher.
        camera_model: COLMAP model fitted during mapping (SIMPLE_RADIAL is COLMAP's default
            for unknown lenses; undistortion turns any model into PINHOLE).
        single_camera: all images share one camera (one capture device).
        camera_params: known intrinsics in ``camera_model``'s parameter order, or None to
            estimate them (from EXIF or a default focal of 1.2 x max(width, height)).
        max_image_size_px: images are downscaled to this longest side for extraction.
        max_num_features: SIFT features kept per image.
        min_num_matches: verified matches a pair needs to join the view graph.
        min_registered_fraction: :class:`DataError` when fewer images register.
        num_threads: CPU threads for every step; 0 = all cores of this machine.
        device: "cpu" or "cuda" (SIFT extraction and matching; mapping is CPU).
        seed: seeds COLMAP's random generator (RANSAC, mapper) for repeatable runs.
        verbose: let COLMAP log INFO lines (otherwise warnings and errors only).
    """

    matcher: str = "auto"
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True
    camera_params: Optional[Tuple[float, ...]] = None
    max_image_size_px: int = 3200
    max_num_features: int = 8192
    min_num_matches: int = 15
    min_registered_fraction: float = 1.0
    num_threads: int = 0
    device: str = "cpu"
    seed: int = 0
    verbose: bool = False

    RANGES: ClassVar[dict] = {
        "exhaustive_max_images": "[1, 1e6]", "sequential_overlap": "[1, 1e4]", "max_image_size_px": "[1, 1e5]",
        "max_num_features": "[1, 1e7]", "min_num_matches": "[1, 1e6]", "min_registered_fraction": "[0, 1]",
        "num_threads": "[0, 1024]", "seed": "[0, 2147483647]", "camera_params": "[-1e7, 1e7]"}
    CHOICES: ClassVar[dict] = {"matcher": MATCHERS, "device": ("cpu", "cuda")}

    def __post_init__(self) -> None:
        check_params(self)  # (every field's range and choices: RANGES / CHOICES above)

    def threads(self) -> int:
        """The thread count actually passed to COLMAP."""
        return self.num_threads or (os.cpu_count() or 1)
