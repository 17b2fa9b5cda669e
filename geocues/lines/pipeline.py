"""The line-cue stage chain: detect -> pair -> match + triangulate + score (per image) ->
tracks -> merge -> colour + sample. Entry point: :func:`extract_line_cues`.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from geocues.lines.config import LineConfig, LineCues
from geocues.lines.detect import detect_all
from geocues.lines.match import match_pair
from geocues.lines.merge import Views, link_tracks, sample_segments
from geocues.lines.pairs import select_neighbors
from geocues.lines.score import LabelMaps, best_per_segment, score_hypotheses
from geocues.lines.tracks import build_lines
from geocues.scene import held_out
from geocues.lines.triangulate import triangulate_matches

log = logging.getLogger(__name__)


def _hypotheses_of_image(i: int, segments: list, neighbors: list, cams: list, labels: LabelMaps,
                         cfg: LineConfig, rejected: Counter, timings: Counter):
    """Match image i with its neighbours, triangulate, score. Returns (best hypothesis per
    segment [N_i] (-1: none), X [H, 2, 3], n_views [H], partner view [H], partner seg [H],
    support [H, K])."""
    hyp_X, hyp_a, hyp_j, hyp_b = [], [], [], []
    for j in neighbors[i]:
        t0 = time.perf_counter()
        ia, jb, counts = match_pair(segments[i], segments[j], cams[i], cams[j], cfg)
        t1 = time.perf_counter()
        X, ok, counts_t = triangulate_matches(segments[i].segs[ia], cams[i], segments[j].segs[jb], cams[j], cfg)
        timings["lines_match"] += t1 - t0
        timings["lines_triangulate"] += time.perf_counter() - t1
        rejected.update(counts)
        rejected.update(counts_t)
        hyp_X.append(X[ok]), hyp_a.append(ia[ok]), hyp_j.append(np.full(int(ok.sum()), j)), hyp_b.append(jb[ok])
    if not hyp_X or sum(len(a) for a in hyp_a) == 0:
        return None
    X, a, jv, b = (np.concatenate(v) for v in (hyp_X, hyp_a, hyp_j, hyp_b))
    t0 = time.perf_counter()
    n_views, n_check, support = score_hypotheses(X, jv, i, neighbors[i], labels, cfg)
    timings["lines_score"] += time.perf_counter() - t0
    ratio = (n_views - 2) / np.maximum(n_check - 2, 1)
    return best_per_segment(a, n_views, ratio, len(segments[i])), X, n_views, ratio, jv, b, support


def extract_line_cues(scene, cfg: LineConfig | None = None, cache_dir: Path | None = None) -> LineCues:
    """3D line cues of ``scene`` (a :class:`geocues.scene.Scene`), paper §4.1.

    2D segments (cached per image in ``cache_dir`` when given), view pairs, candidate matches,
    two-view triangulation with LIMAP's weak epipolar checks, multi-view scoring, tracks fitted
    to all their segment planes, duplicates merged, lines with fewer than ``cfg.min_views``
    supporting views dropped; colour = multi-view mean; samples every ``cfg.sample_step`` m."""
    cfg = cfg or LineConfig()
    cfg.validate()
    if len(scene.cameras) == 0:
        raise ValueError(f"scene {scene.root} has no cameras")
    log.info("lines: config %s", cfg)
    timings: Counter = Counter()
    rejected: Counter = Counter()
    t0 = time.perf_counter()
    segments, det = detect_all(scene, cfg, cache_dir)
    timings["lines_detect"] = time.perf_counter() - t0
    cams = scene.cameras
    per_image = {"names": [c.name for c in cams], **{k: v for k, v in det.items() if k != "cached"},
                 "cached_2d": det["cached"]}
    rejected["duplicates_2d"] = int(sum(det["duplicates_2d"]))
    rejected["images_without_segments"] = int(sum(n == 0 for n in det["segments"]))
    t0 = time.perf_counter()
    # the scene is read with every view (test_every 0): the held-out split to leave out is the option's
    use = [c.index for c in cams if cfg.use_test_views or not held_out(c.index, cfg.test_every)]
    neighbors, pair_stats = select_neighbors(scene, cfg, use)
    timings["lines_pairs"] = time.perf_counter() - t0
    rejected["images_without_neighbors"] = pair_stats["images_without_neighbors"]

    offsets = np.r_[0, np.cumsum([len(s) for s in segments])]
    N = int(offsets[-1])
    node_X = np.full((N, 2, 3), np.nan)
    node_nv = np.zeros(N, np.int64)
    node_ratio = np.zeros(N)
    node_view = np.repeat(np.arange(len(cams)), np.diff(offsets))
    node_seg = np.arange(N) - offsets[node_view]
    edges, n_hyp = [], np.zeros(len(cams), np.int64)
    labels = LabelMaps(segments, cams, cfg)
    for i in tqdm(use, desc="lines: match + triangulate", unit="img", leave=False):
        res = _hypotheses_of_image(i, segments, neighbors, cams, labels, cfg, rejected, timings)
        if res is None:
            continue
        best, X, n_views, ratio, jv, b, support = res
        n_hyp[i] = len(X)
        a = np.nonzero(best >= 0)[0]
        h = best[a]
        few = n_views[h] < cfg.min_seed_views
        weak = ~few & (ratio[h] < cfg.min_support_ratio)
        rejected["few_views"] += int(few.sum())
        rejected["low_support_ratio"] += int(weak.sum())
        a, h = a[~(few | weak)], h[~(few | weak)]
        nodes = offsets[i] + a
        node_X[nodes], node_nv[nodes], node_ratio[nodes] = X[h], n_views[h], ratio[h]
        edges.append(np.stack([nodes, offsets[jv[h]] + b[h]], 1))
        r, k = np.nonzero(support[h] >= 0)
        nb = neighbors[i][k]
        edges.append(np.stack([nodes[r], offsets[nb] + support[h][r, k]], 1))
    per_image["hypotheses"] = n_hyp.tolist()
    per_image["pairs"] = [len(n) for n in neighbors]

    t0 = time.perf_counter()
    views = Views(cams)
    valid = node_nv >= cfg.min_seed_views
    per_image["segments_with_3d_hypothesis"] = np.bincount(node_view[valid], minlength=len(cams)).tolist()
    edges = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    rank = node_nv + node_ratio  # supporting views, then the support ratio
    mem_node, mem_track, n_isolated = link_tracks(node_X, valid, node_view, rank, edges, views, cfg)
    rejected["isolated_tracks"] += n_isolated
    if len(mem_track) == 0:
        log.info("lines: no 2D segment has a hypothesis with >= %d supporting views", cfg.min_seed_views)
        timings["lines_tracks"] = time.perf_counter() - t0
        return LineCues.empty(dict(rejected), dict(timings), per_image)
    timings["lines_tracks"] += time.perf_counter() - t0
    seg3d, track_views, colors = build_lines(mem_node, mem_track, node_X, rank, node_view, node_seg,
                                             segments, views, labels, cfg, rejected, timings)
    points, point_line = sample_segments(seg3d, cfg.sample_step)
    cues = LineCues(seg3d, np.array([len(v) for v in track_views], np.int64), track_views, colors,
                    points, colors[point_line] if len(points) else np.zeros((0, 3), np.float32),
                    point_line, np.zeros((len(points), 3), np.float32), dict(rejected), dict(timings),
                    per_image)
    log.info("lines: %d 3D lines (%.1f m, %d samples) from %d images; rejected %s; %s",
             len(cues), float(cues.lengths().sum()), len(points), len(use), dict(rejected),
             {k: round(v, 2) for k, v in timings.items()})
    return cues

