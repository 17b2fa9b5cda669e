"""Rasterizer benchmark (`splat bench`): forward + backward time and memory per backend and size.

One iteration is what training does per view: ``render()`` (torch projection + compositing + the
per-pixel depth/normal combination), a loss on RGB, expected depth and normal, and
``loss.backward()``. Each configuration also times compositing alone (``composite_s``): the
backend's ``composite()`` on the inputs ``render()`` gives it (recorded once, detached), a sum of
its outputs and the backward, so that the projection's share is ``seconds_per_iter - composite_s``
(roughly: the per-pixel depth/normal combination and the loss are in the first only).

The Gaussians lie on the surfaces of a procedural room (a box room with
furniture-like boxes, normals facing the free space): points sampled by area on its triangles,
tangent scales from nearest-neighbour distances, flat along the surface normal, random colours
and opacities; the camera stands inside the room looking at walls and furniture.

Each configuration runs in a fresh process (``spawn``), so that its peak memory is measured on its
own: ``peak_rss_mb`` is ``ru_maxrss`` after the timed iterations minus ``ru_maxrss`` after building
the scene (resource.getrusage; torch's allocations are included, unlike tracemalloc). A parent-side
timeout turns a configuration that hangs into a "skipped (timeout ...)" entry, and a backend whose
iteration already exceeded ``max_iter_s`` on a smaller problem skips the larger ones.

Timings on a machine shared with other processes vary several-fold: the result records the load
average before and after, and each run's process gets ``OMP_WAIT_POLICY=PASSIVE`` by default
(spin-waiting OpenMP threads are many times slower when a core is taken by someone else). With
more runnable processes than cores, ``--num-threads 1`` can beat the default thread count.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import os
import platform
import resource
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)

QUICK_SIZES = ((64, 48), (96, 72))
QUICK_COUNTS = (2000, 5000)


@dataclass
class BenchConfig:
    """Options of the rasterizer benchmark."""

    sizes: tuple[tuple[int, int], ...] = ((128, 96), (256, 192), (640, 480))
    """Image sizes (width, height) in pixels."""
    counts: tuple[int, ...] = (10_000, 50_000, 200_000)
    """Numbers of Gaussians placed on the room's surfaces."""
    backends: tuple[str, ...] = ("torch", "cpu")
    """Compositing backends to time ("torch", "cpu"; on a GPU "cuda" = the CUDA kernels and
    "torch-cuda" = the torch backend there)."""
    iters: int = 5
    """Timed iterations per configuration (the median is reported)."""
    warmup: int = 1
    """Untimed iterations before timing."""
    budget_s: float = 60.0
    """Time budget per configuration: fewer timed iterations (at least 1) when they would exceed it."""
    max_iter_s: float = 30.0
    """A backend slower than this per iteration skips every larger configuration."""
    timeout_s: float = 600.0
    """A configuration's process is stopped after this many seconds (reported as skipped)."""
    num_threads: int = 0
    """torch / OpenMP threads in each run (0: torch's default, all cores)."""
    omp_wait_policy: str = "passive"
    """OMP_WAIT_POLICY of each run ("passive": idle threads sleep, which a shared machine needs;
    "": keep the environment's)."""
    sh_degree: int = 3
    """SH degree of the Gaussians' colours."""
    seed: int = 0
    """Seed of the scene (positions, colours, opacities)."""
    quick: bool = False
    """Tiny sizes and counts for a smoke test (overrides sizes and counts)."""


# ----------------------------------------------------------------------------------------------
# The scene: a box room with furniture, Gaussians on its surfaces, a camera inside.

ROOM = (6.0, 5.0, 3.0)  # metres, x in [0, 6], y in [0, 5], z in [0, 3] (z up)
FURNITURE = (((0.3, 0.3, 0.0), (1.3, 2.3, 0.5)),  # bed
             ((4.0, 3.6, 0.0), (5.7, 4.7, 0.75)),  # table
             ((5.4, 0.2, 0.0), (5.9, 1.4, 1.9)),  # cabinet
             ((2.5, 4.5, 0.0), (3.7, 4.95, 1.2)))  # shelf


def box_triangles(lo, hi, inward: bool) -> np.ndarray:
    """[12, 3, 3] triangles of an axis-aligned box, normals (by winding) out of it, or into it."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[lo[0] if i & 1 == 0 else hi[0], lo[1] if i & 2 == 0 else hi[1],
                         lo[2] if i & 4 == 0 else hi[2]] for i in range(8)])
    # faces as corner quads, counter-clockwise seen from outside
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = []
    for a, b, c, d in quads:
        tris += [(a, b, c), (a, c, d)] if not inward else [(a, c, b), (a, d, c)]
    return corners[np.array(tris)]


def room_triangles() -> np.ndarray:
    """[F, 3, 3] triangles of the benchmark room (inward shell + outward furniture boxes)."""
    parts = [box_triangles((0, 0, 0), ROOM, inward=True)]
    parts += [box_triangles(lo, hi, inward=False) for lo, hi in FURNITURE]
    return np.concatenate(parts)


def surface_gaussians(n: int, sh_degree: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    """``n`` flat Gaussians on the room's surfaces (gsplat naming; log scales, opacity logits)."""
    if n <= 0:
        raise ValueError(f"number of Gaussians must be positive, got {n}")
    rng = np.random.default_rng(seed)
    tris = room_triangles()  # [F, 3, 3]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])  # [F, 3]
    areas = 0.5 * np.linalg.norm(normals, axis=1)
    normals /= 2.0 * areas[:, None]
    face = rng.choice(len(tris), size=n, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)  # uniform barycentrics
    means = (w[:, :, None] * tris[face]).sum(1)  # [n, 3]
    nrm = normals[face]
    # tangent scale: RMS distance to the 3 nearest neighbours (3DGS init); flat along the normal
    dist, _ = cKDTree(means).query(means, k=4)
    s = np.sqrt((dist[:, 1:] ** 2).mean(1)).clip(1e-4, None)  # [n]
    scales = np.stack([s * np.exp(0.2 * rng.standard_normal(n)), s * np.exp(0.2 * rng.standard_normal(n)),
                       0.02 * s], 1)
    # rotation with third axis = normal and a random in-plane angle
    t1 = np.cross(nrm, np.where(np.abs(nrm[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]]))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    ang = rng.uniform(0, 2 * math.pi, n)[:, None]
    a1, a2 = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
    xyzw = Rotation.from_matrix(np.stack([a1, a2, nrm], 2)).as_quat()
    nb = (sh_degree + 1) ** 2 - 1
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return {
        "means": f32(means),
        "quats": f32(xyzw[:, [3, 0, 1, 2]]),  # xyzw -> wxyz (project convention)
        "scales": f32(np.log(scales)),
        "opacities": f32(np.log(p := rng.uniform(0.2, 0.95, n)) - np.log1p(-p)),
        "sh0": f32((rng.random((n, 1, 3)) - 0.5) / 0.28209479177387814),
        "shN": f32(0.05 * rng.standard_normal((n, nb, 3))),
    }


BENCH_EYE = (1.8, 0.9, 1.6)


def bench_camera(width: int, height: int, eye: tuple[float, float, float] = BENCH_EYE):
    """A camera at ``eye`` inside the room looking at the far corner's walls and furniture (70 deg wide)."""
    from splat.camera import Camera

    eye, target = np.asarray(eye, dtype=np.float64), np.array([5.0, 4.2, 0.9])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera x, y, z axes in world (OpenCV)
    f = 0.5 * width / math.tan(math.radians(35.0))
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera.from_Rt(K, R, -R @ eye, width, height)


TRAIN_EYES = (BENCH_EYE, (2.4, 1.2, 1.4), (1.5, 1.6, 1.8), (2.0, 0.7, 1.2))


@torch.no_grad()
def target_views(truth: dict[str, torch.Tensor], width: int, height: int, device: str | torch.device = "cpu",
                 sh_degree: int | None = None, eyes=TRAIN_EYES) -> list:
    """Views (splat.views.View) whose image, depth prior (median depth where alpha > 0.5) and normal
    prior are renders of the Gaussians ``truth`` from ``eyes``: a training problem with exact
    targets and no files (train-step tests, `bench/train_step_bench.py`)."""
    from splat.rasterize import render
    from splat.views import View

    params = {k: v.to(device) for k, v in truth.items()}
    views = []
    for k, eye in enumerate(eyes):
        cam = bench_camera(width, height, eye).to(device)
        out = render(params, cam, sh_degree=sh_degree)
        covered = out["alpha"] > 0.5
        depth = torch.where(covered, out["median_depth"], torch.zeros_like(out["median_depth"]))
        normal = torch.where(covered[..., None], out["normal"], torch.zeros_like(out["normal"]))
        views.append(View(index=k, name=f"view{k}.png", camera=cam, rgb=out["rgb"].clamp(0, 1),
                          depth_prior=depth, normal_prior=normal))
    return views


# ----------------------------------------------------------------------------------------------
# One configuration, in its own process.

def _loss(out: dict[str, torch.Tensor]) -> torch.Tensor:
    """L1 on RGB (target grey), expected depth (target 3 m) and normal (target facing the camera)."""
    facing = torch.tensor([0.0, 0.0, -1.0], device=out["rgb"].device)
    return ((out["rgb"] - 0.5).abs().mean() + 0.1 * (out["depth"] - 3.0).abs().mean()
            + 0.5 * (out["normal"] - facing).abs().mean())


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _composite_inputs(params: dict[str, torch.Tensor], camera, backend: str) -> tuple[tuple, dict]:
    """The arguments ``render()`` passes to ``composite()`` (one no-grad render), for timing it alone."""
    import splat.rasterize as rasterize

    captured = {}
    real = rasterize.composite

    def spy(*args, **kwargs):
        captured["args"], captured["kwargs"] = args, kwargs
        return real(*args, **kwargs)

    rasterize.composite = spy
    try:
        with torch.no_grad():
            rasterize.render(params, camera, backend=backend)
    finally:
        rasterize.composite = real
    return captured["args"], captured["kwargs"]


def time_composite(params: dict[str, torch.Tensor], camera, backend: str, n_iters: int, warmup: int,
                   sync) -> list[tuple[float, float]]:
    """(forward, backward) seconds of ``composite()`` alone per timed iteration, on render()'s inputs."""
    from splat.composite import composite

    args, kwargs = _composite_inputs(params, camera, backend)
    # means2d, conics, opacities, features require grad; depths, radii, width, height do not
    leaves = [a.detach().clone().requires_grad_() for a in args[:4]]
    bg = kwargs["background"].detach().clone().requires_grad_()
    med = kwargs["median_features"].detach().clone().requires_grad_()
    rest = dict(kwargs, background=bg, median_features=med)
    times = []
    for it in range(warmup + n_iters):
        sync()
        t0 = time.perf_counter()
        out = composite(*leaves, *args[4:], **rest)
        loss = out.features.sum() + out.alpha.sum() + out.median.sum()
        sync()
        t1 = time.perf_counter()
        loss.backward()
        sync()
        t2 = time.perf_counter()
        for t in (*leaves, bg, med):
            t.grad = None
        if it >= warmup:
            times.append((t1 - t0, t2 - t1))
    return times


def _cpu_build() -> str | None:
    """Which build of the C++ extension the `cpu` backend uses here ("avx2", "baseline" or, built
    without OpenMP, "baseline-serial"; None if none)."""
    try:
        from splat.cpu_ext import OPENMP, SIMD
    except ImportError:
        return None
    return SIMD if OPENMP else f"{SIMD}-serial"


def time_config(backend: str, width: int, height: int, n: int, cfg: BenchConfig) -> dict:
    """Time ``cfg.warmup + k`` iterations of render + loss + backward; the measured entry."""
    from splat.composite import available_backends
    from splat.rasterize import render

    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    device = torch.device("cuda" if backend in ("torch-cuda", "cuda") else "cpu")
    name = "torch" if backend == "torch-cuda" else backend
    if device.type == "cuda" and not torch.cuda.is_available():
        return {"status": "skipped (no CUDA device)"}
    if name not in available_backends():
        return {"status": f"skipped ({name} backend unavailable here)"}
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    params = {k: v.to(device).requires_grad_() for k, v in surface_gaussians(n, cfg.sh_degree, cfg.seed).items()}
    camera = bench_camera(width, height).to(device)
    rss0 = _rss_mb()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    fwd, bwd, visible = [], [], 0
    n_timed = cfg.iters
    for it in range(cfg.warmup + cfg.iters):
        if it >= cfg.warmup + n_timed:
            break
        sync()
        t0 = time.perf_counter()
        out = render(params, camera, backend=name)
        loss = _loss(out)
        sync()
        t1 = time.perf_counter()
        loss.backward()
        sync()
        t2 = time.perf_counter()
        for p in params.values():
            p.grad = None
        visible = int(out["visible"].sum())
        if it < cfg.warmup:
            # fewer timed iterations when the budget would not hold them (at least one)
            n_timed = max(1, min(cfg.iters, int(cfg.budget_s // max(t2 - t0, 1e-9))))
            continue
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    total = [f + b for f, b in zip(fwd, bwd)]
    comp = time_composite(params, camera, name, len(total), cfg.warmup, sync)
    entry = {
        "status": "ok",
        "seconds_per_iter": statistics.median(total),
        "forward_s": statistics.median(fwd),
        "backward_s": statistics.median(bwd),
        "times": total,
        "composite_s": statistics.median(f + b for f, b in comp),
        "composite_forward_s": statistics.median(f for f, _ in comp),
        "composite_backward_s": statistics.median(b for _, b in comp),
        "n_visible": visible,
        "peak_rss_mb": _rss_mb() - rss0,
    }
    if device.type == "cuda":
        entry["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return entry


def _worker(args: tuple, queue) -> None:
    try:
        queue.put(time_config(*args))
    except Exception as exc:  # noqa: BLE001 - reported as the configuration's status
        queue.put({"status": f"failed ({type(exc).__name__}: {exc})"})


def _run_isolated(backend: str, width: int, height: int, n: int, cfg: BenchConfig) -> dict:
    """time_config in a fresh spawned process (own peak RSS), stopped after cfg.timeout_s."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_worker, args=((backend, width, height, n, cfg), queue), daemon=True)
    saved = os.environ.get("OMP_WAIT_POLICY")
    if cfg.omp_wait_policy:  # read by OpenMP when the child loads torch
        os.environ["OMP_WAIT_POLICY"] = cfg.omp_wait_policy.upper()
    try:
        proc.start()
    finally:
        if saved is None:
            os.environ.pop("OMP_WAIT_POLICY", None)
        else:
            os.environ["OMP_WAIT_POLICY"] = saved
    try:
        entry = queue.get(timeout=cfg.timeout_s)
    except Exception:  # noqa: BLE001 - queue.Empty: the process hung or died
        entry = {"status": f"skipped (timeout after {cfg.timeout_s:.0f} s or crash, exit code {proc.exitcode})"}
    proc.join(timeout=10)
    if proc.is_alive():
        proc.terminate()
        proc.join()
    return entry


def run_bench(cfg: BenchConfig = BenchConfig(), json_out: Path | None = None) -> dict:
    """Run every (backend, size, count) configuration; return (and optionally write) the results."""
    sizes, counts = (QUICK_SIZES, QUICK_COUNTS) if cfg.quick else (cfg.sizes, cfg.counts)
    for w, h in sizes:
        if w <= 0 or h <= 0:
            raise ValueError(f"image sizes must be positive, got {w}x{h}")
    for b in cfg.backends:
        if b not in ("torch", "cpu", "cuda", "torch-cuda"):
            raise ValueError(f"backend must be one of torch, cpu, cuda, torch-cuda, got {b!r}")
    started = time.time()
    result = {
        "config": asdict(cfg),
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "torch": torch.__version__, "threads": cfg.num_threads or torch.get_num_threads(),
                    "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                    "cpu_build": _cpu_build(),
                    "loadavg_start": os.getloadavg()},
        "memory_note": "peak_rss_mb = ru_maxrss after the timed iterations minus ru_maxrss after "
                       "building the scene, in a fresh process per configuration",
        "runs": [],
    }
    jobs = sorted(((w, h, n) for (w, h) in sizes for n in counts), key=lambda j: j[0] * j[1] * j[2])
    for backend in cfg.backends:
        too_slow: list[tuple[int, int, int, str]] = []  # configs whose iteration exceeded max_iter_s
        for w, h, n in jobs:
            slower = [why for (w2, h2, n2, why) in too_slow if w * h >= w2 * h2 and n >= n2]
            if slower:
                entry = {"status": f"skipped ({slower[0]})"}
            else:
                log.info("bench %s %dx%d %d Gaussians", backend, w, h, n)
                entry = _run_isolated(backend, w, h, n, cfg)
                sec = entry.get("seconds_per_iter")
                if entry["status"] != "ok" or sec > cfg.max_iter_s:
                    why = (f"{w}x{h}, {n} took {sec:.1f} s/iter > {cfg.max_iter_s:.0f} s" if sec
                           else f"{w}x{h}, {n}: {entry['status']}")
                    too_slow.append((w, h, n, why))
            result["runs"].append({"backend": backend, "width": w, "height": h, "n_gaussians": n, **entry})
    for run in result["runs"]:  # speed-up over the torch backend on the CPU, same size and count
        ref = [r for r in result["runs"] if r["backend"] == "torch" and r["status"] == "ok"
               and (r["width"], r["height"], r["n_gaussians"]) == (run["width"], run["height"], run["n_gaussians"])]
        if run["status"] == "ok" and ref:
            run["speedup_vs_torch"] = ref[0]["seconds_per_iter"] / run["seconds_per_iter"]
    result["machine"]["loadavg_end"] = os.getloadavg()
    result["wall_s"] = time.time() - started
    if json_out is not None:
        json_out = Path(json_out)
        json_out.parent.mkdir(parents=True, exist_ok=True)
        tmp = json_out.with_suffix(json_out.suffix + ".tmp")
        tmp.write_text(json.dumps(result, indent=2))
        tmp.replace(json_out)
    return result


def format_table(result: dict) -> str:
    """The results as a fixed-width text table (comp: compositing alone, forward + backward; peak
    MB: GPU memory for runs on a GPU, the process's resident memory otherwise)."""
    lines = [f"{'backend':<11}{'size':>9}{'gaussians':>10}{'visible':>9}{'s/iter':>9}{'fwd':>8}"
             f"{'bwd':>8}{'comp':>8}{'peak MB':>9}{'speed-up':>9}  status"]
    for r in result["runs"]:
        size = f"{r['width']}x{r['height']}"
        if r["status"] != "ok":
            lines.append(f"{r['backend']:<11}{size:>9}{r['n_gaussians']:>10}{'':>60}  {r['status']}")
            continue
        sp = f"{r['speedup_vs_torch']:.1f}x" if "speedup_vs_torch" in r else "-"
        lines.append(f"{r['backend']:<11}{size:>9}{r['n_gaussians']:>10}{r['n_visible']:>9}"
                     f"{r['seconds_per_iter']:>9.3f}{r['forward_s']:>8.3f}{r['backward_s']:>8.3f}"
                     f"{r.get('composite_s', float('nan')):>8.3f}"
                     f"{r.get('peak_cuda_mb', r['peak_rss_mb']):>9.0f}{sp:>9}  ok ({len(r['times'])} timed)")
    m = result["machine"]
    lines.append(f"threads {m['threads']}, load average {m['loadavg_start'][0]:.1f} at start, "
                 f"{m['loadavg_end'][0]:.1f} at end, {result['wall_s']:.0f} s in all")
    return "\n".join(lines)
