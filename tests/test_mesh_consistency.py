"""`--tsdf.consistent-views`: a rendered depth is fused only where neighbouring renders agree
(splat.mesh_run.consistent_depths, the forward-backward check of `geocues mvs`).

A depth one view alone renders (a floater fitted to that photo, in front of the wall) is dropped and
the agreeing surface kept; with the option unset nothing changes; hard cases (no depth, no
neighbour, NaN-free) stay finite."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cues_synth import make_room_scene, render
from geocues.scene import Scene
from splat.mesh import TSDFConfig
from splat.mesh_run import consistent_depths


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = make_room_scene(tmp_path_factory.mktemp("cons") / "room", n_views=24, w=96, h=72, priors="none")
    cams = Scene.load(root, check_priors=False).cameras
    depths = [render(c.K, c.R, c.t, c.width, c.height)[1] for c in cams]
    return cams, depths


def test_a_depth_only_one_view_renders_is_dropped_and_the_surface_kept(room):
    cams, exact = room
    depths = [d.copy() for d in exact]
    patch = (slice(20, 40), slice(30, 60))
    depths[0][patch] *= 0.7  # a floater in front of the wall, in view 0 only
    tsdf = TSDFConfig(consistent_views=1)
    kept = consistent_depths(cams, depths, tsdf)
    assert len(kept) == len(depths) and all(k.shape == d.shape for k, d in zip(kept, depths))
    assert (kept[0][patch] == 0).mean() > 0.95  # the floater goes
    outside = np.ones_like(depths[0], bool)
    outside[patch] = False
    valid = exact[0] > 0
    # the wall around it and the other views stay (a neighbour agrees); the parts of the frame no
    # neighbour sees are the only other losses
    assert (kept[0][outside & valid] > 0).mean() > 0.7
    others = np.concatenate([(k[d > 0] > 0) for k, d in zip(kept[1:], depths[1:])])
    assert others.mean() > 0.7
    for k, d in zip(kept, depths):  # kept values are the rendered values, untouched
        np.testing.assert_array_equal(k[k > 0], d[k > 0])
    # the stricter the vote, the fewer depths are fused (these views overlap their two neighbours
    # by about half the frame)
    strict = consistent_depths(cams, depths, replace(tsdf, consistent_views=2))
    assert sum((k > 0).sum() for k in strict) < sum((k > 0).sum() for k in kept)
    assert (strict[0][patch] == 0).all()


def test_views_without_depth_or_neighbours_give_no_error_and_no_depth(room):
    cams, exact = room
    depths = [np.zeros_like(d) for d in exact]
    depths[3] = exact[3].copy()
    depths[3][0, 0] = np.nan  # a NaN render is never fused
    kept = consistent_depths(cams, depths, TSDFConfig(consistent_views=1))
    assert all(np.isfinite(k).all() for k in kept)
    assert all((k == 0).all() for k in kept)  # nobody agrees with view 3: every neighbour is empty
    one = consistent_depths(cams[:1], exact[:1], TSDFConfig(consistent_views=1))  # no neighbour at all
    assert (one[0] == 0).all()


def test_the_option_is_checked():
    TSDFConfig().validate()  # unset: every pixel is fused
    with pytest.raises(ValueError, match="--tsdf.consistent-views"):
        TSDFConfig(consistent_views=5, consistency_neighbours=4).validate()
    with pytest.raises(ValueError, match="--tsdf.consistent-views"):
        TSDFConfig(consistent_views=0).validate()
    with pytest.raises(ValueError, match="positive"):
        TSDFConfig(consistent_views=1, consistency_rel_depth=0).validate()


def _sheet_over_wall():
    """Gaussians: an opaque wall at z = 3 m filling the view and a sheet of opacity 0.45 at z = 2 m over
    its left part. There alpha is ~1, the expected depth ~2.55 m (a blend of the two) and the median
    depth 3 m (transmittance is still 0.55 behind the sheet): a mixed pixel, as at a silhouette."""
    import torch

    def grid(xs, ys, z, opacity):
        x, y = np.meshgrid(xs, ys)
        n = x.size
        return {"means": torch.tensor(np.stack([x.ravel(), y.ravel(), np.full(n, z)], 1), dtype=torch.float32),
                "scales": torch.log(torch.tensor([[0.08, 0.08, 0.001]]).repeat(n, 1)),
                "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                "opacities": torch.full((n,), float(np.log(opacity / (1 - opacity)))),
                "sh0": torch.full((n, 1, 3), 0.5), "shN": torch.zeros((n, 0, 3))}

    wall = grid(np.arange(-2.4, 2.41, 0.1), np.arange(-1.8, 1.81, 0.1), 3.0, 0.99)
    sheet = grid(np.arange(-1.5, -0.09, 0.1), np.arange(-1.2, 1.21, 0.1), 2.0, 0.45)
    return {k: torch.cat([wall[k], sheet[k]]) for k in wall}


def test_max_depth_spread_leaves_out_mixed_pixels_and_keeps_the_rest():
    from types import SimpleNamespace

    from splat.mesh_run import fuse_cameras

    cam = SimpleNamespace(K=np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), R=np.eye(3), t=np.zeros(3),
                          width=64, height=48, world_to_camera=np.eye(4))
    params = _sheet_over_wall()
    tsdf = TSDFConfig(voxel_size=0.05, min_component_diag=0.0)
    z_all = np.asarray(fuse_cameras(params, [cam], 0, tsdf).vertices)[:, 2]
    z_kept = np.asarray(fuse_cameras(params, [cam], 0, replace(tsdf, max_depth_spread=0.02)).vertices)[:, 2]
    blend = lambda z: ((z > 2.3) & (z < 2.8)).sum()  # noqa: E731
    assert blend(z_all) > 100  # unfiltered: a surface where no Gaussian is
    assert blend(z_kept) == 0
    assert (np.abs(z_kept - 3.0) < 0.05).sum() > 0.3 * (np.abs(z_all - 3.0) < 0.05).sum()  # the wall stays
    assert np.isfinite(z_kept).all()
    with pytest.raises(ValueError, match="--tsdf.max-depth-spread"):
        TSDFConfig(max_depth_spread=0.0).validate()
