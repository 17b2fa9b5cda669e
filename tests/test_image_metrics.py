"""PSNR / SSIM against hand-computed values and a plain numpy/scipy SSIM; the LPIPS hook."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from evaluation.image_metrics import (evaluate_images, gaussian_window, load_image, load_lpips, lpips,
                                      psnr, ssim)


def reference_ssim(x: np.ndarray, y: np.ndarray, padding: str) -> float:
    """Straightforward SSIM: 2D Gaussian (11, sigma 1.5) correlation per channel with scipy."""
    k = np.arange(11) - 5
    g = np.exp(-(k**2) / (2 * 1.5**2))
    g /= g.sum()
    w2 = np.outer(g, g)
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(x.shape[2]):
        a, b = x[:, :, ch], y[:, :, ch]
        f = lambda t: ndimage.correlate(t, w2, mode="constant", cval=0.0)
        mu_a, mu_b = f(a), f(b)
        saa, sbb, sab = f(a * a) - mu_a**2, f(b * b) - mu_b**2, f(a * b) - mu_a * mu_b
        m = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
        if padding == "valid":
            m = m[5:-5, 5:-5]
        vals.append(m)
    return float(np.mean(vals))


class TestPSNR:
    def test_identical_is_inf(self):
        img = torch.rand(16, 20, 3)
        assert psnr(img, img.clone()) == math.inf

    def test_constant_offset_known_value(self):
        ref = 0.2 + 0.6 * torch.rand(24, 32, 3, dtype=torch.float64)
        # MSE = 0.1^2 = 0.01 -> PSNR = 10 log10(1 / 0.01) = 20 dB
        assert psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-9)

    def test_random_noise_matches_formula(self):
        gen = torch.Generator().manual_seed(0)
        ref = torch.rand(40, 30, 3, generator=gen)
        img = (ref + 0.05 * torch.randn(40, 30, 3, generator=gen)).clamp(0, 1)
        mse = np.mean((img.numpy().astype(np.float64) - ref.numpy()) ** 2)
        assert psnr(img, ref) == pytest.approx(10 * np.log10(1.0 / mse), rel=1e-9)
        assert 20 < psnr(img, ref) < 35

    def test_bad_shapes(self):
        with pytest.raises(ValueError, match=r"\(4, 4, 3\) vs \(4, 5, 3\)"):
            psnr(torch.rand(4, 4, 3), torch.rand(4, 5, 3))
        with pytest.raises(ValueError, match=r"\[H, W, C\]"):
            psnr(torch.rand(4, 4), torch.rand(4, 4))
        with pytest.raises(ValueError, match="float"):
            psnr(torch.zeros(4, 4, 3, dtype=torch.uint8), torch.zeros(4, 4, 3, dtype=torch.uint8))


class TestSSIM:
    def test_window(self):
        g = gaussian_window(11, 1.5)
        assert g.shape == (11,) and float(g.sum()) == pytest.approx(1.0)
        assert int(torch.argmax(g)) == 5 and float(g[0]) == pytest.approx(float(g[10]))
        with pytest.raises(ValueError):
            gaussian_window(10, 1.5)

    def test_identical_is_one(self):
        img = torch.rand(32, 32, 3)
        assert ssim(img, img.clone()) == pytest.approx(1.0, abs=1e-6)

    @pytest.mark.parametrize("padding", ["same", "valid"])
    def test_matches_numpy_reference(self, padding):
        rng = np.random.default_rng(1)
        x = rng.random((48, 40, 3))
        y = np.clip(x + 0.3 * rng.standard_normal(x.shape), 0, 1)
        ours = ssim(torch.from_numpy(y), torch.from_numpy(x), padding=padding)
        assert ours == pytest.approx(reference_ssim(y, x, padding), abs=1e-10)
        assert 0.2 < ours < 0.95  # a real, non-trivial value
        # float32 input gives the same value to float32 precision
        ours32 = ssim(torch.from_numpy(y).float(), torch.from_numpy(x).float(), padding=padding)
        assert ours32 == pytest.approx(ours, abs=1e-5)

    def test_padding_modes_differ_only_at_border(self):
        rng = np.random.default_rng(2)
        x, y = rng.random((40, 40, 3)), rng.random((40, 40, 3))
        same = ssim(torch.from_numpy(x), torch.from_numpy(y), padding="same")
        valid = ssim(torch.from_numpy(x), torch.from_numpy(y), padding="valid")
        assert same != valid

    def test_noise_lowers_ssim_monotonically(self):
        gen = torch.Generator().manual_seed(3)
        ref = torch.rand(32, 32, 3, generator=gen)
        noise = torch.randn(32, 32, 3, generator=gen)
        vals = [ssim(ref + s * noise, ref) for s in (0.01, 0.05, 0.2)]
        assert vals[0] > vals[1] > vals[2]


class TestLPIPSHook:
    def test_no_weights_explains(self):
        with pytest.raises(ValueError, match="downloads no weights"):
            load_lpips(None)

    def test_missing_file_names_path(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="nope.pt"):
            load_lpips(tmp_path / "nope.pt")

    def test_torchscript_model_is_used(self, tmp_path):
        class L1(torch.nn.Module):  # stand-in network: mean |x - y| per image
            def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
                return (x - y).abs().mean(dim=(1, 2, 3))

        path = tmp_path / "fake_lpips.pt"
        with pytest.warns(DeprecationWarning):  # torch.jit is deprecated in torch 2.13
            torch.jit.script(L1()).save(str(path))
        model = load_lpips(path)
        ref = torch.full((8, 8, 3), 0.5)
        # inputs are mapped to [-1, 1]: an offset of 0.1 becomes 0.2
        assert lpips(ref + 0.1, ref, model) == pytest.approx(0.2, abs=1e-6)

    def test_not_a_model_file(self, tmp_path):
        path = tmp_path / "garbage.pt"
        path.write_bytes(b"not a model")
        with pytest.raises(ValueError, match="garbage.pt"):
            load_lpips(path)


def test_evaluate_images_from_files(tmp_path):
    import cv2

    rng = np.random.default_rng(4)
    ref = (rng.random((20, 24, 3)) * 255).astype(np.uint8)
    img = np.clip(ref.astype(int) + 10, 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "ref.png"), ref[:, :, ::-1])
    cv2.imwrite(str(tmp_path / "img.png"), img[:, :, ::-1])
    loaded = load_image(tmp_path / "ref.png")
    assert loaded.shape == (20, 24, 3) and loaded.dtype == torch.float32
    np.testing.assert_allclose(loaded.numpy(), ref / 255.0, atol=1e-6)  # RGB order kept
    out = evaluate_images([tmp_path / "img.png"], [tmp_path / "ref.png"])
    mse = np.mean((img / 255.0 - ref / 255.0) ** 2)
    assert out["n_images"] == 1 and out["lpips"] is None
    assert out["psnr"] == pytest.approx(10 * np.log10(1 / mse), rel=1e-5)
    with pytest.raises(FileNotFoundError, match="missing.png"):
        evaluate_images([tmp_path / "missing.png"], [tmp_path / "ref.png"])
