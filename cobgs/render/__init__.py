"""Rendering: the rasterizer (ops, build, the PyTorch oracle), cameras, SH colours, scene renders, turntables and the viewer's packing.

Public names of the modules below are importable from the package too, lazily (importing
``cobgs.render`` loads nothing heavy).
"""

from __future__ import annotations

from cobgs._lazy import lazy_getattr

_WHERE = {
    'ALPHA_MAX': 'reference',
    'ALPHA_MIN': 'reference',
    'BYTES_PER_GAUSSIAN': 'splat_pack',
    'C0': 'sh',
    'C1': 'sh',
    'C2': 'sh',
    'C3': 'sh',
    'CFLAGS': '_build',
    'CSRC': '_build',
    'CUDA_FLAGS': '_build',
    'Camera': 'camera',
    'FIELDS': 'splat_pack',
    'FRUSTUM_SLACK': 'reference',
    'LDFLAGS': '_build',
    'LOWPASS_PX2': 'reference',
    'MAX_DEGREE': 'sh',
    'NEAR_PLANE': 'reference',
    'RasterOutput': 'rasterize',
    'TILE_SIZE': 'reference',
    'T_MIN': 'reference',
    'bin_tiles': '_ops',
    'bin_tiles_reference': 'reference',
    'bin_tiles_tight': '_ops',
    'blend': '_ops',
    'blend_reference': 'reference',
    'budget_count': 'splat_pack',
    'build_key': '_build',
    'cache_root': '_build',
    'check_serves': '_ops',
    'cuda_plan': '_build',
    'ensure_loaded': '_ops',
    'eval_sh': 'sh',
    'extension_name': '_build',
    'gauss_blur': '_ops',
    'has_cuda_kernels': '_build',
    'is_loaded': '_ops',
    'keep_order': 'splat_pack',
    'load_extension': '_build',
    'num_coeffs': 'sh',
    'object_center': 'turntable',
    'object_turntables': 'turntable',
    'orbit_cameras': 'turntable',
    'pack': 'splat_pack',
    'photometric_loss_grad': '_ops',
    'project': '_ops',
    'project_reference': 'reference',
    'quat_to_rotmat': 'reference',
    'rasterize_native': '_ops',
    'rasterize_reference': 'reference',
    'render': 'image',
    'render_image': 'image',
    'render_turntable': 'turntable',
    'rgb_to_sh0': 'sh',
    'scene_extent': 'camera',
    'serves': '_ops',
    'sh0_to_rgb': 'sh',
    'sh_basis': 'sh',
    'sh_colors': '_ops',
    'sh_to_color': 'sh',
    'ssim_mean_grad': '_ops',
    'tile_grid': 'reference',
    'tile_rects': 'reference',
    'unpack': 'splat_pack',
    'unpacked_model': 'splat_pack',
    'write_animation': 'turntable',
}

__all__ = sorted(_WHERE)

__getattr__ = lazy_getattr(__name__, _WHERE, globals())
