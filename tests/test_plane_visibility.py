"""geocues.plane_visibility: plane points the other views' priors put behind a surface are dropped."""

from pathlib import Path

import numpy as np
import pytest

from geocues.plane_visibility import behind_and_agree, visible_mask
from geocues.scene import Camera


def _camera(index, x, w=64, h=48, f=50.0):
    """A camera at (x, 0, 0) looking down +z."""
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(index, index + 1, f"{index}.png", Path(f"{index}.png"), w, h, K, np.eye(3), np.array([-x, 0, 0.0]))


@pytest.fixture()
def views():
    """Three views of a wall at z = 2 whose priors see it (every 4th pixel); view 2's prior has a hole on
    its right half."""
    cams = [_camera(i, x) for i, x in enumerate((-0.2, 0.0, 0.2))]
    priors = {i: np.full((12, 16), 2.0) for i in range(3)}
    priors[2][:, 8:] = 0.0
    return cams, priors


def test_points_behind_the_surface_the_priors_see_are_dropped(views):
    cams, priors = views
    pts = np.array([[0.0, 0.0, 2.0],     # on the wall: every view agrees
                    [0.0, 0.0, 3.0],     # behind it in every view: dropped
                    [0.0, 0.0, 1.0],     # in front (free space is not tested): kept
                    [0.0, 0.0, 2.08],    # within 5 % of the depth: agrees
                    [50.0, 0.0, 3.0]])   # outside every image: no vote
    behind, agree = behind_and_agree(pts, cams, priors, 4, 0.05)
    assert behind.tolist() == [0, 3, 0, 0, 0] and agree.tolist() == [3, 0, 0, 3, 0]
    assert visible_mask(behind, agree, 2).tolist() == [True, False, True, True, True]


def test_a_point_needs_min_views_hiding_it_and_more_than_agree(views):
    cams, priors = views
    pt = np.array([[0.4, 0.0, 3.0]])  # behind the wall; in view 2 it falls in the prior's hole
    behind, agree = behind_and_agree(pt, cams, priors, 4, 0.05)
    assert behind.tolist() == [2]
    assert not visible_mask(behind, agree, 2)[0] and visible_mask(behind, agree, 3)[0]
    assert visible_mask(np.array([2]), np.array([2]), 2)[0]  # as many agree: kept
    nan = {i: np.full((12, 16), np.nan) for i in range(3)}  # no prior depth anywhere: no vote, no NaN
    assert behind_and_agree(pt, cams, nan, 4, 0.05)[0].tolist() == [0]


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        behind_and_agree(np.zeros((4, 2)), [], {}, 4, 0.05)
    with pytest.raises(ValueError, match="stride"):
        behind_and_agree(np.zeros((4, 3)), [], {}, 0, 0.05)
