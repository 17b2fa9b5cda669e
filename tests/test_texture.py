"""Weak-texture regions: segmentation + SIFT keypoint density (paper §4.1)."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.texture import (TextureConfig, keypoint_density, load_or_compute, local_keypoint_density,
                             weak_texture_regions)


def _half_textured(w: int = 320, h: int = 240, seed: int = 0) -> np.ndarray:
    """Left half: a smooth plain colour; right half: blocky random texture (many SIFT keypoints)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.float32)
    img[:, : w // 2] = (0.8, 0.75, 0.7)
    img[:, : w // 2] *= np.linspace(0.9, 1.0, w // 2)[None, :, None]  # gentle shading
    blocks = rng.random((h // 8 + 1, w // 16 + 1, 3)).astype(np.float32)
    tex = cv2.resize(blocks, (w, h), interpolation=cv2.INTER_NEAREST)[:, : w - w // 2]
    img[:, w // 2:] = cv2.GaussianBlur(tex, (3, 3), 0.8)
    return img


class TestKeypointDensity:
    def test_counts_per_segment(self):
        labels = np.zeros((10, 20), np.int32)
        labels[:, 10:] = 1
        kp = np.array([[2.0, 3.0], [12.0, 1.0], [15.2, 8.7], [19.4, 9.4]])  # (x, y)
        np.testing.assert_allclose(keypoint_density(labels, kp), [1000 / 100, 3000 / 100])

    def test_local_density(self):
        d = local_keypoint_density(np.array([[10.0, 10.0]]), (21, 21), 5)
        assert d[10, 10] == pytest.approx(1000 / 25) and d[0, 0] == 0

    def test_bad_shape(self):
        with pytest.raises(ValueError, match=r"\[H, W\]"):
            keypoint_density(np.zeros((2, 2, 2), np.int32), np.zeros((0, 2)))


class TestWeakTextureRegions:
    @pytest.mark.parametrize("method", ["graph", "slic"])
    def test_finds_the_plain_half(self, method):
        img = _half_textured()
        wt = weak_texture_regions(img, TextureConfig(method=method))
        weak = wt.regions >= 0
        assert wt.regions.shape == img.shape[:2]
        assert weak[:, :150].mean() > 0.6, "the plain half should be mostly weak"
        assert weak[:, 170:].mean() < 0.02, "the textured half must not be weak"
        assert wt.n_regions >= 1 and np.all(wt.density < 1.0) and wt.n_keypoints > 50

    def test_resolution_independent(self):
        import cv2

        img = _half_textured(640, 480)
        small = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
        a = weak_texture_regions(img, TextureConfig()).weak_fraction
        b = weak_texture_regions(small, TextureConfig()).weak_fraction
        assert a > 0.3 and abs(a - b) < 0.1

    def test_plain_image_and_uint8(self):
        img = np.full((120, 160, 3), 140, np.uint8)
        wt = weak_texture_regions(img, TextureConfig())
        assert wt.n_keypoints == 0 and wt.weak_fraction > 0.8 and wt.n_regions == 1

    def test_bad_input(self):
        with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
            weak_texture_regions(np.zeros((10, 10)), TextureConfig())
        with pytest.raises(ValueError, match="unknown segmentation"):
            weak_texture_regions(np.zeros((32, 32, 3)), TextureConfig(method="sam"))  # type: ignore[arg-type]


class TestCache:
    def test_reused_and_keyed_by_config(self, tmp_path):
        import cv2

        img = _half_textured(160, 120)
        path = tmp_path / "im.png"
        cv2.imwrite(str(path), (img[:, :, ::-1] * 255).astype(np.uint8))
        calls = []

        def load():
            calls.append(1)
            return cv2.imread(str(path))[:, :, ::-1]

        a, hit_a = load_or_compute(path, load, TextureConfig(), tmp_path / "cache", (160, 120))
        b, hit_b = load_or_compute(path, load, TextureConfig(), tmp_path / "cache", (160, 120))
        assert (hit_a, hit_b) == (False, True) and len(calls) == 1
        np.testing.assert_array_equal(a.regions, b.regions)
        np.testing.assert_array_equal(a.density, b.density)
        _, hit_c = load_or_compute(path, load, TextureConfig(weak_density=0.5), tmp_path / "cache", (160, 120))
        assert not hit_c and len(calls) == 2
