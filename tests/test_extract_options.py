"""`geocues extract` options a user sweeps (found by a sweep of 150 runs): a NaN, an inf or a value that
gave empty cues or garbage is refused before any work, with one line naming the option."""

from __future__ import annotations

import re

import pytest

from geocues.extract import ExtractConfig
from geocues.extract_checks import check_extract_options
from geocues.presets import EXTRACT_PRESETS, apply_overrides, extract_preset_config


@pytest.mark.parametrize("name", list(EXTRACT_PRESETS))
def test_every_preset_passes(name):
    check_extract_options(extract_preset_config(name))


@pytest.mark.parametrize("change, said", [
    ({"line.support_dist_px": float("inf")}, "--line.support-dist-px must be a finite number, got inf"),  # OverflowError
    ({"plane.cut_px": float("inf")}, "--plane.cut-px must be a finite number, got inf"),
    ({"sor.sor_std_ratio": float("nan")}, "--sor.sor-std-ratio must be a finite number, got nan"),  # removed every point
    ({"line.pair_depths_m": (1.0, float("nan"))}, "--line.pair-depths-m must be a finite number, got nan"),
    ({"line.support_angle_deg": -5.0}, "--line.support-angle-deg is an angle and must be in [0, 180] degrees"),
    ({"sor.sor_neighbors": 1}, "--sor.sor-neighbors must be >= 2, got 1"),  # Open3D removed every point
    ({"texture.work_width": 0}, "--texture.work-width must be >= 16 px, got 0"),  # became 16 in silence
    ({"plane.voxel_size": 0.0}, "--plane.voxel-size must be > 0, got 0.0"),  # divide by zero, 0 planes
    ({"plane.min_ray_cos": 2.0}, "--plane.min-ray-cos is a share and must be in [0, 1], got 2.0"),
    ({"plane.max_planes": 0}, "--plane.max-planes must be >= 1, got 0"),
    ({"line.max_depth_m": -1.0}, "--line.max-depth-m must be > 0, got -1.0"),
    ({"texture.erode_px": -4}, "--texture.erode-px must be >= 0 (0: off), got -4"),
    ({"align.max_anchors": 10}, "--align.max-anchors (10) must be >= --align.min-anchors (20)"),  # "too few anchors"
])
def test_impossible_options_are_refused_naming_the_flag(change, said):
    with pytest.raises(ValueError, match=re.escape(said)):
        check_extract_options(apply_overrides(ExtractConfig(), change))


def test_the_command_refuses_before_any_work(tmp_path, capsys):
    from cli.geocues_cli import main

    assert main(["extract", str(tmp_path), "-o", str(tmp_path / "cues"), "--line.support-dist-px", "inf"]) == 1
    err = capsys.readouterr().err
    assert "--line.support-dist-px must be a finite number" in err and "Traceback" not in err
    assert not (tmp_path / "cues").exists()
