"""Surface fusion of the images' prior planes (geocues.plane_surfaces, `--plane.fuse-surfaces`): a
weak-texture wall whose images each see one of its border lines gets cues across, not only along
each line; a parallel surface in front of it stays apart; nothing but an anchored surface is cut."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from geocues.plane_surfaces import SurfaceCandidate, fuse_surfaces, group_surfaces
from geocues.planes import PlaneConfig, plane_cues_with_prior
from geocues.scene import Camera

W, H, F = 160, 120, 100.0
WALL_Z = 3.0


def camera(index: int, cx_world: float) -> Camera:
    """A camera at (cx_world, 0, 0) looking along +z (R = I) at the wall z = 3."""
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    return Camera(index, index + 1, f"{index}.png", Path(f"{index}.png"), W, H, K, np.eye(3),
                  -np.array([cx_world, 0.0, 0.0]))


def line(x: float, z: float = WALL_Z, n: int = 60) -> np.ndarray:
    """Samples of a vertical line (along y) at (x, ., z)."""
    return np.stack([np.full(n, x), np.linspace(-0.8, 0.8, n), np.full(n, z)], axis=1)


def warped_prior(cam: Camera, tilt: float) -> np.ndarray:
    """Aligned prior depth of the wall with a low-frequency warp: z (1 + tilt * u), u in [-1, 1]
    across the image (tilts the prior's plane by a few degrees, as a monocular network's does)."""
    u = (np.arange(W) + 0.5 - W / 2) / (W / 2)
    return np.broadcast_to(WALL_Z * (1.0 + tilt * u)[None, :], (H, W)).astype(np.float32).copy()


@pytest.fixture(scope="module")
def wall():
    """Two images of one wall; each supports one of its two border lines (x = -1.6 and x = 1.6)."""
    cams = [camera(0, -0.8), camera(1, 0.8)]
    anchors = np.concatenate([line(-1.6), line(1.6)])
    group = np.repeat([0, 1], 60)
    seen = [np.flatnonzero(group == 0), np.flatnonzero(group == 1)]
    priors = [warped_prior(cams[0], 0.04), warped_prior(cams[1], -0.04)]
    return cams, anchors, group, seen, priors


def per_image(wall, cfg: PlaneConfig):
    cams, anchors, group, seen, priors = wall
    regions = np.zeros((H, W), np.int32)
    image = np.full((H, W, 3), 0.5, np.float32)
    return [plane_cues_with_prior(cam, image, regions, priors[k], anchors[seen[k]], cfg, seed=k,
                                  anchors_group=group[seen[k]], anchor_ids=seen[k])
            for k, cam in enumerate(cams)]


def covered(xyz: np.ndarray, x_range=(-1.4, 1.4), y_range=(-0.8, 0.8), cell: float = 0.1) -> float:
    """Share of the wall's cells (x, y) between the lines that hold at least one point."""
    xs = np.arange(x_range[0], x_range[1], cell)
    ys = np.arange(y_range[0], y_range[1], cell)
    if len(xyz) == 0:
        return 0.0
    ix = np.floor((xyz[:, 0] - x_range[0]) / cell).astype(int)
    iy = np.floor((xyz[:, 1] - y_range[0]) / cell).astype(int)
    ok = (ix >= 0) & (ix < len(xs)) & (iy >= 0) & (iy < len(ys))
    return len(set(zip(ix[ok], iy[ok]))) / (len(xs) * len(ys))


def test_a_wall_between_two_lines_seen_by_different_images_is_covered_only_with_fusion(wall):
    cams, anchors, group, _, _ = wall
    plain = per_image(wall, PlaneConfig())
    xyz_plain = np.concatenate([p.xyz for p in plain])
    fused_cfg = PlaneConfig(fuse_surfaces=True)
    pp = per_image(wall, fused_cfg)
    assert all(len(p.xyz) == 0 for p in pp)  # with fusion nothing is cut per image ...
    cands = [c for p in pp for c in p.candidates]
    assert len(cands) == 2 and all(len(c.anchor_ids) == 60 for c in cands)
    out, stats = fuse_surfaces(cands, cams, anchors, group, fused_cfg)
    assert stats["surfaces"] == 1 and stats["surfaces_of_several_images"] == 1
    xyz = np.concatenate([o[1] for o in out])
    # ... and the surface pinned by both lines covers the wall between them, on it to a millimetre
    assert covered(xyz) > 0.9 > 0.5 > covered(xyz_plain)
    assert np.abs(xyz[:, 2] - WALL_Z).max() < 2e-3
    assert np.allclose(np.abs(out[0][3][:, 2]), 1.0, atol=1e-3)  # normals of the wall
    # each image's plane, pinned by one line and the warped prior's normal, is tilted: where it is
    # kept at all (near its line) it is off by more than the fused surface anywhere
    assert np.abs(xyz_plain[:, 2] - WALL_Z).max() > 5 * np.abs(xyz[:, 2] - WALL_Z).max()


def test_a_parallel_surface_in_front_stays_apart(wall):
    """A cabinet front 8 cm before the wall (within the prior's warp tolerance), with its own line, seen by a third image: it is not
    pulled onto the wall (its line is not coplanar with the wall's), and the wall is unchanged."""
    cams, anchors, group, seen, priors = wall
    cfg = PlaneConfig(fuse_surfaces=True)
    cands = [c for p in per_image(wall, cfg) for c in p.candidates]
    cab = camera(2, 0.0)
    front = line(0.0, z=WALL_Z - 0.08)
    all_anchors = np.concatenate([anchors, front])
    all_group = np.r_[group, np.full(60, 2)]
    cams3 = cams + [cab]
    z = np.full((H, W), WALL_Z - 0.08, np.float32)
    cab_cands = plane_cues_with_prior(cab, np.full((H, W, 3), 0.5, np.float32), np.zeros((H, W), np.int32), z,
                                      front, cfg, anchors_group=np.full(60, 2), anchor_ids=np.arange(120, 180)
                                      ).candidates
    surfaces = group_surfaces(cands + cab_cands, cams3, all_anchors, all_group, cfg)
    assert sorted(len(s.members) for s in surfaces) == [1, 2]
    out, _ = fuse_surfaces(cands + cab_cands, cams3, all_anchors, all_group, cfg)
    for view, xyz, *_ in out:
        expected = WALL_Z - 0.08 if view == 2 else WALL_Z
        assert np.abs(xyz[:, 2] - expected).max() < 5e-3


def test_a_plane_without_anchors_joins_an_anchored_surface_or_gives_nothing(wall):
    cams, anchors, group, seen, priors = wall
    cfg = PlaneConfig(fuse_surfaces=True)
    cands = [c for p in per_image(wall, cfg) for c in p.candidates]
    third = camera(2, 0.0)
    rows, cols = np.mgrid[0:H:2, 0:W:2]
    lone = SurfaceCandidate.from_camera_plane(third, np.array([0.0, 0.0, 1.0]), -WALL_Z * 1.02, rows.ravel(),
                                              cols.ravel(), np.full(rows.size, WALL_Z * 1.02), np.zeros((rows.size, 3)),
                                              np.zeros(0, np.int64))
    out, stats = fuse_surfaces(cands + [lone], cams + [third], anchors, group, cfg)
    assert stats["candidates_without_surface"] == 0
    third_pts = np.concatenate([o[1] for o in out if o[0] == 2])
    x, y = (cols.ravel() + 0.5 - W / 2) / F * WALL_Z, (rows.ravel() + 0.5 - H / 2) / F * WALL_Z
    between = (np.abs(x) <= 1.6) & (np.abs(y) <= 0.8)  # its pixels inside the lines' hull
    assert len(third_pts) >= 0.95 * between.sum() and np.abs(third_pts[:, 2] - WALL_Z).max() < 2e-3
    out, stats = fuse_surfaces([lone], [cams[0], cams[1], third], anchors, group, cfg)
    assert out == [] and stats == {"surface_candidates": 1, "surfaces": 0, "surfaces_of_several_images": 0,
                                   "candidates_without_surface": 1}


@pytest.mark.parametrize("case", ["empty", "grazing", "behind"])
def test_hard_cases_give_finite_points_or_none(wall, case):
    cams, anchors, group, _, _ = wall
    cfg = PlaneConfig(fuse_surfaces=True)
    cands = [c for p in per_image(wall, cfg) for c in p.candidates]
    if case == "empty":
        assert fuse_surfaces([], cams, anchors, group, cfg) == ([], {"surface_candidates": 0, "surfaces": 0,
                                                                  "surfaces_of_several_images": 0,
                                                                  "candidates_without_surface": 0})
        return
    # a camera looking along the wall (grazing) or away from it (the wall behind it)
    R = np.array([[0, 0, 1.0], [0, 1, 0], [-1, 0, 0]]) if case == "grazing" else np.diag([-1.0, 1.0, -1.0])
    odd = dataclasses.replace(camera(2, 0.0), R=R, t=-R @ np.array([0.0, 0.0, 1.0]))
    rows, cols = np.mgrid[0:H:4, 0:W:4]
    c = SurfaceCandidate.from_camera_plane(odd, np.array([0.0, 0.0, 1.0]), -2.0, rows.ravel(), cols.ravel(),
                                           np.full(rows.size, 2.0), np.zeros((rows.size, 3)), np.zeros(0, np.int64))
    c = dataclasses.replace(c, n=np.array([0.0, 0.0, 1.0]), d=-WALL_Z)  # claims to be the wall
    out, _ = fuse_surfaces(cands + [c], cams + [odd], anchors, group, cfg)
    for _, xyz, rgb, n, plane in out:
        assert np.isfinite(xyz).all() and np.isfinite(n).all() and np.isfinite(plane).all()
    assert all(view != 2 for view, *_ in out)
