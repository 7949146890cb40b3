"""cobgs.rasterize: native C++ ops against the pure-PyTorch reference (cobgs/render/reference.py).

Tolerances. In float64 both backends evaluate the same formulas and differ only in
summation order (matmul vs explicit sums, cumprod vs a running product, the backward's
T = T_after / (1 - α) recovery), i.e. by a few ulp per operation over at most a few
hundred operations: rtol 1e-9 plus an absolute floor of 1e-9 x the largest magnitude in
the compared tensor leaves >1e5 headroom over that, while any formula error shows up at
>= 1e-3. All discrete results (radii, tile lists, contribution counts) must be equal.
In float64 a cut-off decision (α vs 1/255, T vs 1e-4, the radius ceil) could only differ
between backends if a value fell within ~1e-15 of the threshold, which seeded scenes of a
few hundred Gaussians do not produce.
"""

from __future__ import annotations

import math

import pytest
import torch

import cobgs
from cobgs.render import reference as ref
from cobgs.errors import InputError

RTOL64 = 1e-9


def assert_close64(actual, expected, what):
    scale = max(1.0, float(expected.detach().abs().max())) if expected.numel() else 1.0
    torch.testing.assert_close(actual, expected, rtol=RTOL64, atol=1e-9 * scale,
                               msg=lambda m: f"{what}: {m}")


def random_rotation(g, max_angle, dtype):
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=dtype), dim=0)
    angle = max_angle * (2 * torch.rand((), generator=g, dtype=dtype) - 1)
    kx = torch.zeros(3, 3, dtype=dtype)
    kx[0, 1], kx[0, 2], kx[1, 2] = -axis[2], axis[1], -axis[0]
    kx = kx - kx.T
    return torch.eye(3, dtype=dtype) + torch.sin(angle) * kx + (1 - torch.cos(angle)) * kx @ kx


def make_scene(seed, n, width, height, channels=3, dtype=torch.float64, extremes=True,
               spread=1.3):
    """A seeded scene in front of a randomly posed camera.

    Camera-space positions are drawn first (depth 1..5, x/y over ``spread`` x the
    frustum, so many Gaussians straddle or leave the image) and mapped to the world through the
    inverse pose. With ``extremes``: ~10% behind the camera or at the near plane, ~5%
    with one zero scale, ~2% with all scales zero, ~4% huge (hundreds of px), ~5%
    opacity 1 (α clamped at 0.99), ~5% opacity below 1/255.
    """
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * max(width, height)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    R = random_rotation(g, 0.3, dtype)
    t = torch.tensor([0.1, -0.2, 0.5], dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3], viewmat[:3, 3] = R, t

    rnd = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    z = 1 + 4 * rnd(n)
    x = (2 * rnd(n) - 1) * spread * (width / 2 / f) * z
    y = (2 * rnd(n) - 1) * spread * (height / 2 / f) * z
    sigma_px = torch.exp(math.log(0.3) + math.log(20.0) * rnd(n, 3))  # 0.3..6 px
    scales = sigma_px * z[:, None] / f
    opacities = rnd(n)
    if extremes and n:
        kind = torch.randint(0, 100, (n,), generator=g)
        z = torch.where(kind < 7, -3 + 3 * rnd(n), z)  # behind the camera
        z = torch.where((kind >= 7) & (kind < 10), 0.002 + 0.03 * rnd(n), z)  # near plane
        scales[(kind >= 10) & (kind < 15), 0] = 0.0
        scales[(kind >= 15) & (kind < 17)] = 0.0
        scales[(kind >= 17) & (kind < 21)] *= 100.0
        opacities = torch.where((kind >= 21) & (kind < 26), torch.ones_like(opacities),
                                opacities)
        opacities = torch.where((kind >= 26) & (kind < 31), opacities / 300, opacities)
    cam = torch.stack([x, y, z], -1)
    means = (cam - t) @ R  # inverse rigid transform, row vectors
    quats = torch.randn(n, 4, generator=g, dtype=dtype) * (0.5 + rnd(n, 1))  # unnormalised
    features = rnd(n, channels)
    background = rnd(channels)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities,
                features=features, viewmat=viewmat, K=K, width=width, height=height,
                background=background)


DIFF_ARGS = ("means", "quats", "scales", "opacities", "features", "background")


def render_with_grads(scene, backend, pixel_labels=None, num_labels=2, seed=123):
    """Renders, back-propagates a fixed random linear loss, returns (out, grads)."""
    leaves = {k: (v.clone().requires_grad_(True) if k in DIFF_ARGS else v)
              for k, v in scene.items()}
    out = cobgs.rasterize(**leaves, pixel_labels=pixel_labels, num_labels=num_labels,
                          backend=backend)
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(seed)
    # Drawn in float64 whatever the render dtype, so float32 and float64 runs agree.
    gi = torch.randn(out.image.shape, generator=g, dtype=torch.float64).to(out.image.dtype)
    ga = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64).to(out.alpha.dtype)
    loss = (out.image * gi).sum() + (out.alpha * ga).sum()
    grads = {}
    if loss.requires_grad:
        loss.backward()
        grads = {k: leaves[k].grad for k in DIFF_ARGS}
        grads["means2d"] = out.means2d.grad
    return out, grads


SCENES = [
    # (seed, N, W, H, C): random scenes with every kind of extreme; image sizes that are
    # not multiples of the tile size; a one-pixel-wide and a one-pixel-tall image.
    (0, 300, 64, 48, 3),
    (1, 200, 37, 29, 1),
    (2, 150, 50, 40, 5),
    (3, 60, 1, 40, 3),
    (4, 60, 40, 1, 2),
    (5, 400, 17, 16, 3),
]


@pytest.mark.parametrize("seed,n,width,height,channels", SCENES)
def test_forward_and_gradients_match_reference(seed, n, width, height, channels):
    scene = make_scene(seed, n, width, height, channels)
    nat, g_nat = render_with_grads(scene, "native")
    ref_out, g_ref = render_with_grads(scene, "reference")
    assert torch.equal(nat.radii, ref_out.radii)
    visible = int((nat.radii > 0).sum())
    assert visible > 0 or n == 0
    for field in ("image", "alpha", "transmittance", "means2d", "conics", "depths"):
        assert_close64(getattr(nat, field), getattr(ref_out, field), field)
    for name in g_ref:
        assert_close64(g_nat[name], g_ref[name], f"grad {name}")
    # The scene must actually exercise the gradients (not all zero).
    for name in ("means", "quats", "scales", "opacities", "features"):
        assert g_nat[name].abs().max() > 0, name


def test_scene_contains_the_advertised_extremes():
    """The cut-offs the comparison relies on really occur in the test scenes."""
    scene = make_scene(0, 300, 64, 48)
    out = cobgs.rasterize(**scene, backend="native")
    depth = (scene["means"] @ scene["viewmat"][:3, :3].T + scene["viewmat"][:3, 3])[:, 2]
    assert ((depth <= ref.NEAR_PLANE) & (out.radii == 0)).sum() >= 10  # culled: behind/near
    r = out.radii.double()
    m = out.means2d
    straddle = (out.radii > 0) & ((m[:, 0] - r < 0) | (m[:, 0] + r > 64))
    assert straddle.sum() >= 5
    assert (out.radii > 64).sum() >= 3  # huge Gaussians covering the image
    assert ((scene["opacities"] >= 0.99) & (out.radii > 0)).sum() >= 3  # α clamp active
    assert ((scene["opacities"] < 1 / 255) & (out.radii > 0)).sum() >= 3


def test_empty_scene():
    scene = make_scene(0, 0, 20, 10)
    for backend in ("native", "reference"):
        out, grads = render_with_grads(scene, backend)
        torch.testing.assert_close(out.image, scene["background"].expand(10, 20, 3))
        assert torch.equal(out.alpha, torch.zeros(10, 20, dtype=torch.float64))
        assert out.radii.shape == (0,)
        if backend == "native":  # the reference's graph never touches the empty inputs
            assert grads["means"].shape == (0, 3)
        # background gradient = Σ_pixels T_final · dL/dimage, T_final = 1 everywhere
        assert grads["background"].abs().sum() > 0


def test_everything_culled():
    scene = make_scene(1, 20, 30, 20)
    scene["means"] = scene["means"] - 100 * scene["viewmat"][2, :3]  # push behind the camera
    nat, g_nat = render_with_grads(scene, "native")
    _, g_ref = render_with_grads(scene, "reference")
    assert (nat.radii == 0).all()
    torch.testing.assert_close(nat.image, scene["background"].expand(20, 30, 3))
    for name in ("means", "quats", "scales", "opacities", "features"):
        assert (g_nat[name] == 0).all(), name
        assert g_ref[name] is None or (g_ref[name] == 0).all(), name  # None: not in graph


def test_tile_lists_equal_reference():
    from cobgs.render import ops

    scene = make_scene(7, 500, 70, 45)
    for dtype in (torch.float64, torch.float32):
        s = {k: (v.to(dtype) if torch.is_tensor(v) else v) for k, v in scene.items()}
        m2, _, depths, radii = ops.project(s["means"], s["quats"], s["scales"], s["viewmat"],
                                            s["K"], 70, 45)
        # Equal depths must keep index order: duplicate some depths exactly.
        vis = torch.nonzero(radii > 0).flatten()
        depths = depths.clone()
        depths[vis[1::5]] = depths[vis[0::5]][: vis[1::5].numel()]
        off_n, ids_n = ops.bin_tiles(m2, radii, depths, 70, 45)
        off_r, ids_r = ref.bin_tiles_reference(m2, radii, depths, 70, 45)
        assert torch.equal(off_n, off_r) and torch.equal(ids_n, ids_r)
        assert ids_n.numel() > 500


@pytest.mark.parametrize("seed", [0, 5])
def test_label_statistics_match_reference(seed):
    scene = make_scene(seed, 300, 48, 40)
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(-1, 3, (40, 48), generator=g)
    nat = cobgs.rasterize(**scene, pixel_labels=labels, num_labels=3, backend="native")
    rf = cobgs.rasterize(**scene, pixel_labels=labels, num_labels=3, backend="reference")
    assert nat.label_counts.dtype == torch.int32 and nat.label_counts.shape == (300, 3)
    assert nat.label_weights.dtype == torch.float32
    assert torch.equal(nat.label_counts, rf.label_counts)
    assert nat.label_counts.sum() > 1000
    # float32 outputs summed in different orders: a few float32 ulp of the largest sum.
    torch.testing.assert_close(nat.label_weights, rf.label_weights, rtol=1e-5, atol=1e-5)
    # Independent check: Σ_g α·T over the pixels of label k is Σ of their alpha.
    for k in range(3):
        expected = nat.alpha[labels == k].sum().float()
        torch.testing.assert_close(nat.label_weights[:, k].sum(), expected, rtol=1e-5,
                                   atol=1e-4)
    # Labels do not change the render.
    plain = cobgs.rasterize(**scene, backend="native")
    assert torch.equal(plain.image, nat.image)
    assert plain.label_counts is None and plain.label_weights is None


def test_label_counts_follow_the_stopping_rule():
    """Three opaque Gaussians over one pixel: α = 0.99 each, T: 1 → 0.01 → ~1e-4 → stop.

    The second brings T to 1.0000000000000018e-4 (not below 1e-4: blended); the third
    would give 1e-6 < 1e-4, so the pixel stops before it (3DGS rule): counts 1, 1, 0.
    """
    dtype = torch.float64
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]], dtype=dtype)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=dtype)
    scales = torch.full((3, 3), 0.5, dtype=dtype)  # wide: α ≈ o at the centre pixel
    opacities = torch.ones(3, dtype=dtype)
    features = torch.eye(3, dtype=dtype)
    K = torch.tensor([[10.0, 0, 0.5], [0, 10.0, 0.5], [0, 0, 1]], dtype=dtype)
    labels = torch.zeros(1, 1, dtype=torch.int64)
    for backend in ("native", "reference"):
        out = cobgs.rasterize(means, quats, scales, opacities, features, torch.eye(4, dtype=dtype),
                              K, 1, 1, pixel_labels=labels, num_labels=1, backend=backend)
        assert out.label_counts[:, 0].tolist() == [1, 1, 0], backend
        torch.testing.assert_close(out.image[0, 0], torch.tensor([0.99, 0.0099, 0.0],
                                                                 dtype=dtype))
        assert out.transmittance[0, 0] >= 1e-4


def test_single_gaussian_analytic():
    """One isotropic Gaussian on the optical axis, checked against closed forms."""
    dtype = torch.float64
    f, z, s, o = 50.0, 2.0, 0.1, 0.6
    K = torch.tensor([[f, 0, 10.5], [0, f, 8.5], [0, 0, 1]], dtype=dtype)  # mean at pixel (10, 8)
    args = (torch.tensor([[0.0, 0.0, z]], dtype=dtype), torch.tensor([[0.3, 0.0, 0.0, 0.0]],
            dtype=dtype), torch.full((1, 3), s, dtype=dtype), torch.tensor([o], dtype=dtype),
            torch.tensor([[1.0, 2.0]], dtype=dtype), torch.eye(4, dtype=dtype), K, 21, 17)
    var = (f * s / z) ** 2 + 0.3  # EWA: J Σ Jᵀ + 0.3 px²
    lam_max = var + math.sqrt(0.1)  # 3DGS: mid + sqrt(max(0.1, mid² - det)), here mid² = det
    for backend in ("native", "reference"):
        out = cobgs.rasterize(*args, background=torch.tensor([0.5, 0.0], dtype=dtype),
                              backend=backend)
        assert out.radii.tolist() == [math.ceil(3 * math.sqrt(lam_max))]
        torch.testing.assert_close(out.means2d[0], torch.tensor([10.5, 8.5], dtype=dtype))
        torch.testing.assert_close(out.conics[0], torch.tensor([1 / var, 0, 1 / var], dtype=dtype))
        torch.testing.assert_close(out.image[8, 10], torch.tensor([o + 0.5 * (1 - o), 2 * o],
                                                                  dtype=dtype))
        a1 = o * math.exp(-0.5 / var)  # one pixel to the right
        torch.testing.assert_close(out.alpha[8, 11], torch.tensor(a1, dtype=dtype))
        assert out.depths.tolist() == [z]


def test_float32_matches_float64_reference():
    """Native float32 against the float64 reference on a scene without extremes.

    Colours are sums of ~20 terms of size <= 1 computed in float32 (unit roundoff 6e-8),
    so 1e-4 absolute leaves ~100x headroom. A pair within ~1e-6 of the α = 1/255 cut-off
    could flip between precisions and move a pixel by up to 1/255; that would fail this
    test, and this seeded scene has none.
    Gradients: relative to each tensor's largest entry, 1e-3 (float32 accumulation over
    ~50 pairs per Gaussian, with cancellations).
    """
    scene = make_scene(11, 200, 48, 32, extremes=False)
    nat, g_nat = render_with_grads({k: (v.float() if torch.is_tensor(v) else v)
                                    for k, v in scene.items()}, "native")
    rf, g_ref = render_with_grads(scene, "reference")
    assert torch.equal(nat.radii, rf.radii)
    torch.testing.assert_close(nat.image.double(), rf.image, rtol=0, atol=1e-4)
    torch.testing.assert_close(nat.alpha.double(), rf.alpha, rtol=0, atol=1e-4)
    for name in g_ref:
        scale = float(g_ref[name].abs().max())
        torch.testing.assert_close(g_nat[name].double(), g_ref[name], rtol=0,
                                   atol=1e-3 * scale, msg=lambda m: f"{name}: {m}")


def test_gradcheck_native_float64():
    """Finite differences on a tiny scene (smooth region: no pair near a cut-off).

    The outputs (image, alpha, means2d) are reduced to 24 fixed random linear
    combinations, which keeps gradcheck fast while any wrong Jacobian entry still shows
    (it would have to be orthogonal to all 24 random directions).
    """
    scene = make_scene(3, 4, 12, 10, channels=2, extremes=False)
    scene["opacities"] = torch.tensor([0.3, 0.5, 0.7, 0.4], dtype=torch.float64)
    proj = torch.randn(24, 12 * 10 * 3 + 4 * 2, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(0))

    def fn(means, quats, scales, opacities, features, background):
        out = cobgs.rasterize(means, quats, scales, opacities, features, scene["viewmat"],
                              scene["K"], 12, 10, background=background)
        flat = torch.cat([out.image.flatten(), out.alpha.flatten(), out.means2d.flatten()])
        return proj @ flat

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in DIFF_ARGS)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_means2d_gradient_is_in_pixels():
    """means2d.grad equals d(loss)/d(means2d) by finite differences in pixel units."""
    # spread 1: no Gaussian reaches the Jacobian clamp, whose limits also move with cx.
    scene = make_scene(4, 10, 24, 20, extremes=False, spread=1.0)
    out, grads = render_with_grads(scene, "native")
    assert grads["means2d"].shape == (10, 2)
    # Shifting every Gaussian by δ px in x via the principal point moves all means2d by δ.
    delta = 1e-6
    moved = dict(scene)
    moved["K"] = scene["K"].clone()
    moved["K"][0, 2] += delta
    g = torch.Generator().manual_seed(123)
    gi = torch.randn(out.image.shape, generator=g, dtype=torch.float64)
    ga = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64)

    def loss(s):
        o = cobgs.rasterize(**s)
        return float((o.image * gi).sum() + (o.alpha * ga).sum())

    fd = (loss(moved) - loss(scene)) / delta
    visible = out.radii > 0
    assert math.isclose(fd, float(grads["means2d"][visible, 0].sum()), rel_tol=1e-4)


def test_float32_and_float64_both_supported_and_dtype_preserved():
    scene = make_scene(2, 30, 20, 20)
    for dtype in (torch.float32, torch.float64):
        s = {k: (v.to(dtype) if torch.is_tensor(v) else v) for k, v in scene.items()}
        out = cobgs.rasterize(**s)
        assert out.image.dtype == dtype and out.alpha.dtype == dtype
        assert out.radii.dtype == torch.int32


# ----------------------------------------------------------------------------- errors


def _good():
    return make_scene(0, 5, 8, 6)


@pytest.mark.parametrize("backend", ["native", "reference"])
@pytest.mark.parametrize("name,bad,needle", [
    ("means", torch.zeros(5, 2), "means must have shape [*, 3], got [5, 2]"),
    ("quats", torch.zeros(5, 3, dtype=torch.float64), "quats must have shape [5, 4]"),
    ("scales", torch.zeros(4, 3, dtype=torch.float64), "scales must have shape [5, 3]"),
    ("opacities", torch.zeros(5, 1, dtype=torch.float64), "opacities must have shape [5]"),
    ("features", torch.zeros(5, dtype=torch.float64), "features must have shape [N, C]"),
    ("background", torch.zeros(4, dtype=torch.float64), "background must have shape [3]"),
    ("viewmat", torch.eye(3, dtype=torch.float64), "viewmat must have shape [4, 4]"),
    ("K", torch.eye(4, dtype=torch.float64), "K must have shape [3, 3]"),
    ("means", torch.zeros(5, 3, dtype=torch.int64), "means must be float32 or float64"),
    ("quats", torch.zeros(5, 4, dtype=torch.float32), "quats must have dtype torch.float64"),
    ("opacities", [0.5] * 5, "opacities must be a torch.Tensor, got list"),
    ("width", 0, "width must be a positive int, got 0"),
    ("height", 2.5, "height must be a positive int, got 2.5"),
    ("K", torch.tensor([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64), "no skew"),
    ("K", torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64),
     "positive focal lengths"),
    ("viewmat", 2 * torch.eye(4, dtype=torch.float64), "last row [0, 0, 0, 1]"),
    ("quats", torch.zeros(5, 4, dtype=torch.float64, device="meta"), "quats must be on cpu"),
])
def test_bad_input_names_the_argument(backend, name, bad, needle):
    args = _good()
    args[name] = bad
    with pytest.raises(InputError) as info:
        cobgs.rasterize(**args, backend=backend)
    assert needle in str(info.value)


@pytest.mark.parametrize("labels,num_labels,needle", [
    (torch.zeros(6, 8), 2, "pixel_labels must have an integer dtype, got torch.float32"),
    (torch.zeros(6, 7, dtype=torch.int64), 2, "pixel_labels must have shape [6, 8]"),
    (torch.full((6, 8), 2), 2, "pixel_labels must lie in -1..1 (num_labels = 2), got values "
                               "in 2..2"),
    (torch.full((6, 8), -2), 2, "got values in -2..-2"),
    (torch.zeros(6, 8, dtype=torch.int64), 0, "num_labels must be a positive int, got 0"),
])
def test_bad_labels(labels, num_labels, needle):
    with pytest.raises(InputError) as info:
        cobgs.rasterize(**_good(), pixel_labels=labels, num_labels=num_labels)
    assert needle in str(info.value)


def test_bad_backend():
    with pytest.raises(InputError, match='backend must be "native" or "reference"'):
        cobgs.rasterize(**_good(), backend="cuda")


def test_native_ops_reject_bad_tensors_with_named_errors():
    """Direct torch.ops calls (bypassing the Python checks) fail cleanly, naming the tensor."""
    from cobgs.render import ops

    ops.ensure_loaded()
    s = _good()
    with pytest.raises(RuntimeError, match=r"quats must have shape \[5, 4\]"):
        torch.ops.cobgs.project(s["means"], s["quats"][:, :3].contiguous(), s["scales"],
                                s["viewmat"], s["K"], 8, 6, 0.01)
    m2, co, d, r = torch.ops.cobgs.project(s["means"], s["quats"], s["scales"], s["viewmat"],
                                           s["K"], 8, 6, 0.01)
    off, ids = torch.ops.cobgs.bin_tiles(m2, r, d, 8, 6)
    bad_ids = torch.full_like(ids, 99) if ids.numel() else torch.tensor([99], dtype=torch.int32)
    bad_off = off.clone()
    bad_off[-1] = bad_ids.numel()
    with pytest.raises(RuntimeError, match="flat_ids must index Gaussians 0..4"):
        torch.ops.cobgs.blend(m2, co, s["opacities"], s["features"], s["background"], bad_off,
                              bad_ids, 8, 6, None, 2)
    with pytest.raises(RuntimeError, match="pixel_labels must lie in -1..1"):
        torch.ops.cobgs.blend(m2, co, s["opacities"], s["features"], s["background"], off, ids,
                              8, 6, torch.full((6, 8), 5, dtype=torch.int32), 2)
    with pytest.raises(RuntimeError, match="radii must have dtype Long|radii must have dtype"):
        torch.ops.cobgs.bin_tiles(m2, r.long(), d, 8, 6)
