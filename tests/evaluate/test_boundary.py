"""cobgs.evaluate.boundary (issue 57 item 1): the measures of what COB-GS's boundaries depend
on, on hand-built cases whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cobgs.evaluate.boundary import band_psnr, edge_band, straddling_gaussians


def test_the_edge_band_is_the_pixels_near_the_edge():
    m = np.zeros((20, 20), bool)
    m[5:15, 5:15] = True
    band = edge_band(m, 2)
    assert band[5, 10] and band[3, 10] and band[6, 10] and not band[10, 10] and not band[0, 0]
    assert not band[2, 10]  # 3 px outside: beyond the band
    assert not edge_band(np.zeros((4, 4), bool), 2).any() and not edge_band(np.ones((4, 4), bool), 2).any()


def test_band_psnr_reads_only_the_band():
    ref = np.zeros((10, 10, 3), np.uint8)
    img = ref.copy()
    img[0, 0] = 255  # an error outside the band
    band = np.zeros((10, 10), bool)
    band[5, :] = True
    assert band_psnr(img, ref, band) == math.inf
    img[5, 5] = 51  # one band pixel off by 0.2 in every channel: MSE 0.04 / 10
    assert band_psnr(img, ref, band) == pytest.approx(10 * math.log10(1 / (0.04 / 10)))
    assert math.isnan(band_psnr(img, ref, np.zeros((10, 10), bool)))


def test_straddling_gaussians_are_those_whose_footprint_crosses_the_edge():
    from cobgs.gaussians.model import GaussianModel
    from cobgs.render.camera import Camera

    # a camera looking down +z at the origin; three Gaussians at depth 2: one at the mask's edge,
    # one deep inside, one far outside; the mask is the left half of the image
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cam = Camera(K=K, viewmat=torch.eye(4), width=64, height=48)
    means = torch.tensor([[0.0, 0.0, 2.0], [-0.9, 0.0, 2.0], [0.9, 0.0, 2.0]])
    model = GaussianModel(means=means, log_scales=torch.full((3, 3), math.log(0.02)),
                          quats=torch.tensor([[1.0, 0, 0, 0]] * 3), opacity_logits=torch.tensor([2.0, 0.0, -2.0]),
                          sh0=torch.zeros(3, 1, 3), shN=torch.zeros(3, 0, 3))
    mask = np.zeros((48, 64), bool)
    mask[:, :32] = True
    out = straddling_gaussians(model, [cam, cam], [mask, None])
    assert out["straddling"] == 1 and out["mask"].tolist() == [True, False, False] and out["views"] == 1
    assert out["opacity_median"] == pytest.approx(torch.sigmoid(torch.tensor(2.0)).item())
    assert out["scale_median"] == pytest.approx(0.02) and 0 < out["radius_px_median"] < 10
