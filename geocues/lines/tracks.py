"""From linked 2D segments to final 3D lines: seed fit, guided matching in every view, refit,
verification, duplicate merging, colour.

A track is seeded by the best two-view hypothesis of its linked segments, fitted to their planes,
then re-observed: its 3D segment is projected into all views and every consistent 2D segment
joins it (:func:`geocues.lines.score.collect_supports`). The refit line is kept when it is
well conditioned, seen by >= min_views views and distinct viewpoints away from the viewing rays,
and supported in a large enough share of the views that should see it.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from geocues.lines.config import LineConfig
from geocues.lines.merge import (Views, duplicate_pairs, endpoint_params, member_residuals, ray_angle_views,
                                 refine_tracks, robust_extent)
from geocues.lines.score import LabelMaps, collect_supports

log = logging.getLogger(__name__)


def fit_tracks(mem_track: np.ndarray, mem_view: np.ndarray, mem_segs: np.ndarray, P0: np.ndarray,
               u0: np.ndarray, views: Views, cfg: LineConfig) -> dict:
    """Fit every track to its members (see :func:`refine_tracks`) and find its extent (see
    :func:`robust_extent`). Returns per-track arrays: seg3d [T, 2, 3], sigma, groups (distinct
    viewpoints), n_ray (views seeing it away from the rays), n_views (views with inliers),
    rms (inlier endpoint residual, pixels at reference_width), fitted (bool), and the
    per-member ``inlier`` mask."""
    T = len(P0)
    P, u, inlier, sigma, groups = refine_tracks(mem_track, mem_view, mem_segs, P0, u0, views, cfg)
    s, s_ok = endpoint_params(P[mem_track], u[mem_track], mem_segs, mem_view, views)
    use = inlier & s_ok
    lo, hi = robust_extent(mem_track[use], mem_view[use], s[use], T, cfg.extent_min_share)
    seg3d = np.stack([P + lo[:, None] * u, P + hi[:, None] * u], 1)
    fitted = np.isfinite(sigma) & np.isfinite(seg3d).all((1, 2)) & (hi > lo)
    V = len(views.cameras)
    key = np.unique(mem_track[inlier] * V + mem_view[inlier])
    dist, _ = member_residuals(P[mem_track], u[mem_track], mem_segs, mem_view, views)
    dist *= cfg.reference_width / views.width[mem_view]  # pixels at reference_width
    n_in = np.maximum(np.bincount(mem_track[inlier], minlength=T), 1)
    rms = np.sqrt(np.bincount(mem_track[inlier], weights=dist[inlier] ** 2, minlength=T) / n_in)
    return {"seg3d": seg3d, "sigma": sigma, "groups": groups, "fitted": fitted, "inlier": inlier, "rms": rms,
            "n_ray": ray_angle_views(mem_track, mem_view, mem_segs, u, inlier, views, cfg.min_ray_angle_deg),
            "n_views": np.bincount(key // V, minlength=T)}


def accept_tracks(fit: dict, n_visible: np.ndarray, cfg: LineConfig, rejected: Counter) -> np.ndarray:
    """Tracks that pass every check [T] bool; each failing track is counted once, under the
    first reason: track_ill_conditioned (no fit, sigma too large or no extent), few_views_track,
    track_ray_aligned, track_few_viewpoints, track_low_ratio (supported in < min_track_ratio of
    the views it projects into)."""
    ok = fit["fitted"].copy()
    ratio = fit["n_views"] / np.maximum(n_visible, 1)
    for reason, bad in (("track_ill_conditioned", ~fit["fitted"]),
                        ("few_views_track", fit["n_views"] < cfg.min_views),
                        ("track_ray_aligned", fit["n_ray"] < cfg.min_views),
                        ("track_few_viewpoints", fit["groups"] < cfg.min_views),
                        ("track_low_ratio", ratio < cfg.min_track_ratio)):
        rejected[reason] += int((ok & bad).sum())
        ok &= ~bad
    return ok


def exclusive_members(track: np.ndarray, view: np.ndarray, seg: np.ndarray, inlier: np.ndarray,
                      n_views: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Members [M] to keep so that each (view, segment) belongs to one track: among the tracks
    it is an inlier of, the one with the most views (then the smallest sigma). Ghost lines of
    repetitive textures (planks, books) live on segments that belong to real lines; once those
    are taken they fall below min_views."""
    keep = np.zeros(len(track), bool)
    m = np.nonzero(inlier)[0]
    if len(m) == 0:
        return keep
    key = view[m].astype(np.int64) * (int(seg.max()) + 1) + seg[m]
    order = np.lexsort((sigma[track[m]], -n_views[track[m]], key))
    k = key[order]
    first = np.r_[True, k[1:] != k[:-1]]
    keep[m[order[first]]] = True
    return keep


def _segs(segments: list, view: np.ndarray, seg: np.ndarray, field: str = "segs") -> np.ndarray:
    if len(view) == 0:
        return np.zeros((0, 4 if field == "segs" else 3))
    order = np.argsort(view, kind="stable")
    out = np.empty((len(view), 4 if field == "segs" else 3))
    bounds = np.r_[0, np.nonzero(np.diff(view[order]))[0] + 1, len(view)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        idx = order[a:b]
        out[idx] = getattr(segments[view[idx[0]]], field)[seg[idx]]
    return out


def build_lines(mem_node: np.ndarray, mem_track: np.ndarray, node_X: np.ndarray, node_rank: np.ndarray,
                node_view: np.ndarray, node_seg: np.ndarray, segments: list, views: Views,
                labels: LabelMaps, cfg: LineConfig, rejected: Counter,
                timings: Counter) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Seed fit -> guided matching -> refit + checks -> merge duplicates -> refit + checks ->
    colours. Returns (segments [L, 2, 3], supporting views per line, colours [L, 3])."""
    t0 = time.perf_counter()
    T = int(mem_track.max()) + 1
    mem_view, mem_seg = node_view[mem_node], node_seg[mem_node]
    order = np.lexsort((-node_rank[mem_node], mem_track))  # seed: the best-ranked member hypothesis
    first = order[np.r_[True, mem_track[order][1:] != mem_track[order][:-1]]]
    X0 = node_X[mem_node[first]]
    fit = fit_tracks(mem_track, mem_view, _segs(segments, mem_view, mem_seg), X0[:, 0],
                     X0[:, 1] - X0[:, 0], views, cfg)
    seed = np.where(fit["fitted"][:, None, None], fit["seg3d"], X0)
    timings["lines_tracks"] += time.perf_counter() - t0

    t0 = time.perf_counter()
    tr, vw, sg, n_vis = collect_supports(seed, labels, cfg)
    fit = fit_tracks(tr, vw, _segs(segments, vw, sg), seed[:, 0], seed[:, 1] - seed[:, 0], views, cfg)
    ok = accept_tracks(fit, n_vis, cfg, rejected)
    timings["lines_guided"] += time.perf_counter() - t0

    # duplicates: a component of the duplicate graph becomes one track (members united), refitted
    t0 = time.perf_counter()
    good = np.nonzero(ok)[0]
    pairs = good[duplicate_pairs(fit["seg3d"][good], cfg)] if len(good) else np.zeros((0, 2), np.int64)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(T, T))
    _, comp = connected_components(g, directed=False)
    _, group = np.unique(comp[good], return_inverse=True)
    n_groups = int(group.max()) + 1 if len(good) else 0
    rejected["merged_duplicates"] += len(good) - n_groups
    new_id = np.full(T, -1)
    new_id[good] = group
    length = np.linalg.norm(fit["seg3d"][:, 1] - fit["seg3d"][:, 0], axis=-1)
    o = good[np.lexsort((-length[good], new_id[good]))]
    rep = o[np.r_[True, new_id[o][1:] != new_id[o][:-1]]] if len(o) else o  # longest of each group
    m = fit["inlier"] & (new_id[tr] >= 0)
    V, S1 = len(views.cameras), (int(sg.max()) + 1 if len(sg) else 1)
    key = np.unique((new_id[tr[m]] * V + vw[m]) * S1 + sg[m])  # (track, view, segment) once each
    tr, vw, sg = key // S1 // V, key // S1 % V, key % S1
    n_vis_g = np.zeros(n_groups, np.int64)
    np.maximum.at(n_vis_g, new_id[good], n_vis[good])
    if n_groups == 0:
        timings["lines_merge"] += time.perf_counter() - t0
        return np.zeros((0, 2, 3)), [], np.zeros((0, 3), np.float32)
    S0 = fit["seg3d"][rep]
    fit = fit_tracks(tr, vw, _segs(segments, vw, sg), S0[:, 0], S0[:, 1] - S0[:, 0], views, cfg)
    # a 2D segment images one 3D line: it stays only with its strongest track, then refit
    win = exclusive_members(tr, vw, sg, fit["inlier"], fit["n_views"], fit["sigma"])
    rejected["shared_segments_dropped"] += int((fit["inlier"] & ~win).sum())
    tr, vw, sg = tr[win], vw[win], sg[win]
    S0 = np.where(fit["fitted"][:, None, None], fit["seg3d"], S0)
    fit = fit_tracks(tr, vw, _segs(segments, vw, sg), S0[:, 0], S0[:, 1] - S0[:, 0], views, cfg)
    keep = accept_tracks(fit, n_vis_g, cfg, rejected)
    inl = fit["inlier"]
    # colour: mean over views of the mean colour of the track's segments in that view
    key, inv = np.unique(tr[inl] * V + vw[inl], return_inverse=True)
    tv_track, tv_view = key // V, key % V
    col_tv = np.zeros((len(key), 3))
    np.add.at(col_tv, inv, _segs(segments, vw[inl], sg[inl], "colors"))
    col_tv /= np.bincount(inv, minlength=len(key))[:, None]
    n_views = np.bincount(tv_track, minlength=n_groups)
    colors = np.zeros((n_groups, 3))
    np.add.at(colors, tv_track, col_tv)
    colors /= np.maximum(n_views, 1)[:, None]
    idx = np.nonzero(keep)[0]
    split = np.searchsorted(tv_track, idx)
    track_views = [tv_view[a:b].astype(np.int64) for a, b in zip(split, split + n_views[idx])]
    timings["lines_merge"] += time.perf_counter() - t0
    return fit["seg3d"][idx], track_views, np.clip(colors[idx], 0, 1).astype(np.float32)
