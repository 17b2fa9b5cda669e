"""Seconds per training iteration: the whole `splat train` step, not the rasterizer alone.

    python bench/train_step_bench.py --name cpu2 [--device cpu|cuda] [--sizes 320x240 640x480] \
        [--counts 50000 100000 300000] [--iters 20] [--variants baseline fused-adam today]

One iteration is ``splat.train.train_step``: render, the IndoorGS loss terms (L_rgb, L_d, L_n,
L_s and L_nc, all on; not the anchored-depth term L_a, which these views have no anchor for and
which adds one element-wise pass over the image), backward, Adam on every parameter, and the density control's gradient
bookkeeping (no refine step falls inside the timed window; refine steps are rare and their cost
is in the trainer's own report). The problem has no files: flat Gaussians on a benchmark room's
surfaces (``splat.bench.surface_gaussians``) rendered from four cameras give the targets and the
depth/normal priors, and training starts from a perturbed copy. Median seconds of ``--iters``
steps after 3 warm-up steps (CUDA synchronised), and the median of each stage of the step (render =
projection + compositing forward; loss = every loss term's forward; backward = all gradients,
compositing and projection included; optimizer; density), from ``train_step(stage_s=...)``.
Each configuration runs once per ``--variants`` entry side by side, so old and new are timed under
the same conditions: "baseline" (torch's Adam and autograd through the torch SSIM: the training
step when issue 15 was filed; with ``--baseline-kernels REV`` also that commit's compositing kernels,
built by bench/old_kernels.py, and its torch pixel maps), "fused-adam" (torch's single-kernel Adam only), "today" (the
defaults: fused Adam and the C++ SSIM and L_nc of splat/losses_cpu.py, on a GPU the CUDA loss kernels
of splat/losses_cuda.py; on a GPU also the render maps compiled by splat/compiled.py, `splat train
--compile`), "fused-loss" ("today" without compiling: the default of `splat train` on a GPU).
On a GPU the steps are timed in a pass without the stage clocks (which synchronise at every stage
boundary, as training does not) and the stages in a second pass; ``syncs_per_step`` counts how often
one step makes the host wait for the GPU (torch's sync debug mode).
Writes ``bench/results/train_step_<name>.json``. Not part of the default tests.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import statistics
import sys
import time
import warnings
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from bench.doc_markers import replace_block  # noqa: E402
from geocues.atomic import atomic_path  # noqa: E402
from splat import compiled  # noqa: E402
from splat.camera_opt import CameraRefiner  # noqa: E402
from splat.bench import _cpu_build, surface_gaussians, target_views  # noqa: E402
from splat.losses import LossConfig  # noqa: E402
from splat.strategy import IndoorStrategy, IndoorStrategyConfig  # noqa: E402
from splat.frozen import colour_step  # noqa: E402
from splat.train import LearningRates, TrainConfig, make_optimizers, render_view, train_step  # noqa: E402


@dataclass
class StepBench:
    name: str
    """Result name: bench/results/train_step_NAME.json."""
    device: str = "cpu"
    sizes: tuple[str, ...] = ("320x240", "640x480")
    counts: tuple[int, ...] = (50_000, 100_000, 300_000)
    iters: int = 20
    sh_degree: int = 3
    backend: str = "auto"
    variants: tuple[str, ...] = ("baseline", "today")
    """Implementations to time side by side (names of :data:`VARIANTS`)."""
    docs: bool = False
    """write the table into docs/training.md (between its train-step markers)."""
    docs_marker: str = "train-step"
    """the markers' name (``<!-- NAME -->`` ... ``<!-- /NAME -->``)."""
    detail: bool = True
    """Also split the stages (CPU): projection and compositing forward and backward, each loss term's
    forward, and the rest of the backward (the loss terms' gradients), by timing those functions."""
    camera_opt: bool = False
    """Also refine the views' poses and focal (TrainConfig.pose_opt / focal_opt, splat/camera_opt.py): the
    projection then runs in torch, which carries the camera's gradient."""
    baseline_kernels: str = ""
    """The "baseline" variant composites with the C++ kernels of this commit (bench/old_kernels.py), e.g.
    2a93836 (those of the day issue 15 was filed, unchanged until then since 0c0625d), and render's pixel
    maps in torch where that commit had no C++ kernel for them; empty: today's."""
    profile: str = ""
    """Also profile 10 steps of each configuration with torch.profiler and append the operator table
    (sorted by device time on CUDA, by CPU time otherwise) to this file."""


STAGES = ("render", "loss", "backward", "optimizer", "density")
LOSS_TERMS = ("rgb_loss", "depth_pcc_loss", "anchored_depth_loss", "normal_prior_loss", "flatten_loss",
              "depth_normal_consistency_loss", "multiview_ncc_loss")


@contextlib.contextmanager
def detail_timers(acc: dict[str, float]):
    """Within the block, the CPU projection and compositing autograd Functions and every loss term
    add their seconds to ``acc`` (projection_fwd/bwd, composite_fwd/bwd, loss:<term>); the bench
    patches them, the library is not touched."""
    from splat import composite_cpu, losses, project_cpu

    def timed(fn, key):
        def wrapper(*args, **kw):
            t = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                acc[key] = acc.get(key, 0.0) + time.perf_counter() - t
        return wrapper

    saved = []
    for cls, name in ((project_cpu._ProjectCPU, "projection"), (composite_cpu._CompositeCPU, "composite")):
        for attr, suffix in (("forward", "fwd"), ("backward", "bwd")):
            saved.append((cls, attr, cls.__dict__[attr]))
            setattr(cls, attr, staticmethod(timed(getattr(cls, attr), f"{name}_{suffix}")))
    for term in LOSS_TERMS:
        saved.append((losses, term, getattr(losses, term)))
        setattr(losses, term, timed(getattr(losses, term), f"loss:{term.removesuffix('_loss')}"))
    try:
        yield acc
    finally:
        for owner, attr, value in saved:
            setattr(owner, attr, value)
# The same training step computed by other code: (TrainConfig.adam, LossConfig.kernels, whether
# splat/compiled.py compiles the GPU's loss terms and render maps, TrainConfig.compile; no effect on the CPU).
# "frozen": today's step once `splat train --geometry-until` has stopped the geometry (splat/frozen.py's
# colour step: L_rgb, the colours' gradient, Adam on sh0 and shN).
VARIANTS = {"baseline": ("torch", "torch", False), "fused-adam": ("fused", "torch", False),
            "fused-loss": ("fused", "fused", False), "today": ("fused", "fused", True),
            "frozen": ("fused", "fused", True)}


def time_config(width: int, height: int, n: int, cfg: StepBench, variant: str) -> dict:
    adam, kernels, compile_gpu = VARIANTS[variant]
    compiled.enable(compile_gpu)
    with _composite_kernels(cfg.baseline_kernels if variant == "baseline" else "") as composite_kernels:
        row = _time_config(width, height, n, cfg, variant, adam, kernels, compile_gpu)
    row["composite_kernels"] = composite_kernels
    return row


@contextlib.contextmanager
def _composite_kernels(rev: str):
    """Within the block the CPU compositing runs the kernels of commit ``rev`` (today's if empty), and
    render's pixel maps the torch code where ``rev`` predates their C++ kernel; yields a label."""
    import subprocess

    from splat import composite_cpu, cpu_ext, maps_cpu
    from splat.rasterize import pixel_maps

    if not rev:
        yield f"today ({cpu_ext.COMPOSITE_LANES} float lanes)"
        return
    from bench.old_kernels import composite_kernels_at

    saved = composite_cpu._ext, maps_cpu.pixel_maps_cpu
    composite_cpu._ext = composite_kernels_at(rev)
    had_maps = subprocess.run(["git", "cat-file", "-e", f"{rev}:splat/maps_cpu.py"], cwd=REPO,
                              capture_output=True).returncode == 0
    if not had_maps:
        maps_cpu.pixel_maps_cpu = lambda f, m, a, eps: pixel_maps(f, m, a)
    try:
        yield rev + ("" if had_maps else ", torch pixel maps")
    finally:
        composite_cpu._ext, maps_cpu.pixel_maps_cpu = saved


def _time_config(width: int, height: int, n: int, cfg: StepBench, variant: str, adam: str, kernels: str,
                 compile_gpu: bool) -> dict:
    truth = surface_gaussians(n, sh_degree=cfg.sh_degree, seed=0)
    views = target_views(truth, width, height, cfg.device, sh_degree=cfg.sh_degree)
    g = torch.Generator().manual_seed(0)
    start = {k: v.clone() for k, v in truth.items()}
    start["sh0"] += 0.3 * torch.randn(start["sh0"].shape, generator=g)
    start["means"] += 0.005 * torch.randn(start["means"].shape, generator=g)
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.to(cfg.device)) for k, v in start.items()})
    optimizers = make_optimizers(params, LearningRates(), 3.0, adam)
    strategy = IndoorStrategy(IndoorStrategyConfig(max_gaussians=0))  # 30k schedule: steps 1..N are before refining
    state = strategy.initialize_state(3.0)
    state["cue_type"] = (torch.arange(n) % 3).to(cfg.device)
    tcfg = TrainConfig(device=cfg.device, backend=cfg.backend, sh_degree=cfg.sh_degree, adam=adam)
    loss_cfg = replace(LossConfig(), nc_from_iter=0, kernels=kernels)  # every term on
    refiner = (CameraRefiner(len(views), 3.0, True, True, tcfg.pose_lr, tcfg.focal_lr, cfg.device)
               if cfg.camera_opt else None)
    cuda = cfg.device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    times, stages = [], []
    detail = cfg.detail and cfg.device == "cpu"

    def one_step(step: int, stage_s: dict | None) -> Tensor:
        k = step % len(views)
        view = refiner.view(k, views[k]) if refiner is not None else views[k]
        if variant == "frozen":
            loss, _, _ = colour_step(params, optimizers, view, cfg.sh_degree, loss_cfg, step,
                                     partial(render_view, cfg=tcfg))
            return loss
        loss, _, _ = train_step(params, optimizers, strategy, state, view, step,
                                cfg.sh_degree, tcfg, loss_cfg, g, stage_s=stage_s, refiner=refiner)
        return loss

    # On a GPU the stage clocks synchronise at every stage boundary, which a training run does not:
    # the step is timed in a pass without them (synchronised only at its end), the stages in a second one
    for step in range(1, cfg.iters + 4):
        stage_s: dict[str, float] = {}
        sync()
        t0 = time.perf_counter()
        with detail_timers(stage_s) if detail else contextlib.nullcontext():
            loss = one_step(step, None if cuda else stage_s)
        sync()
        if step > 3:
            times.append(time.perf_counter() - t0)
            stages.append(stage_s)
        if not math.isfinite(float(loss)):
            raise RuntimeError(f"non-finite loss at step {step} ({width}x{height}, {n})")
    if cuda:
        stages = []
        for step in range(cfg.iters + 4, 2 * cfg.iters + 4):
            stage_s = {}
            one_step(step, stage_s)
            stages.append(stage_s)
        syncs = _count_syncs(lambda: one_step(2 * cfg.iters + 4, None))
    if cfg.profile:
        _profile(params, optimizers, strategy, state, views, tcfg, loss_cfg, g, cfg, f"{width}x{height} {n} {variant}")
    row = {"width": width, "height": height, "n": n, "variant": variant + ("+camera-opt" if cfg.camera_opt else ""),
           "adam": adam, "loss_kernels": kernels,
           "compiled": compile_gpu and cfg.device.startswith("cuda"), "median_s": statistics.median(times),
           "min_s": min(times), "max_s": max(times),
           "stages_s": {k: statistics.median(st.get(k, 0.0) for st in stages) for k in STAGES
                        if variant != "frozen"}}  # the colour step has no stage clock
    if detail:  # the backward's rest: the loss terms' gradients and the autograd glue
        for st in stages if variant != "frozen" else ():
            st["backward_rest"] = st["backward"] - st.get("composite_bwd", 0.0) - st.get("projection_bwd", 0.0)
        keys = sorted({k for st in stages for k in st} - set(STAGES))
        row["detail_s"] = {k: statistics.median(st.get(k, 0.0) for st in stages) for k in keys}
    if cuda:
        row["syncs_per_step"] = syncs
        row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
        torch.cuda.reset_peak_memory_stats()
    return row


def _count_syncs(fn) -> int:
    """How many times ``fn`` made the host wait for the GPU (torch's sync debug mode warns at each)."""
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return sum("called a synchronizing" in str(w.message) for w in caught)


def _profile(params, optimizers, strategy, state, views, tcfg, loss_cfg, g, cfg: StepBench, title: str) -> None:
    from torch.profiler import ProfilerActivity, profile

    cuda = cfg.device.startswith("cuda")
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        for step in range(10):
            train_step(params, optimizers, strategy, state, views[step % len(views)], 100 + step, cfg.sh_degree,
                       tcfg, loss_cfg, g)
        if cuda:
            torch.cuda.synchronize()
    table = prof.key_averages().table(sort_by="cuda_time_total" if cuda else "cpu_time_total", row_limit=40)
    with open(cfg.profile, "a") as f:
        f.write(f"## {title} (10 steps)\n{table}\n")


def main(cfg: StepBench) -> dict:
    unknown = [v for v in cfg.variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown --variants {unknown}; choose from {list(VARIANTS)}")
    rows = []
    print(f"{'size':>8s} {'n':>7s} {'variant':>10s} {'s/iter':>7s}  " + " ".join(f"{k:>9s}" for k in STAGES))
    for size in cfg.sizes:
        w, h = (int(v) for v in size.split("x"))
        for n in cfg.counts:
            for variant in cfg.variants:
                row = time_config(w, h, n, cfg, variant)
                rows.append(row)
                print(f"{size:>8s} {n:>7d} {variant:>10s} {row['median_s']:7.3f}  "
                      + " ".join(f"{row['stages_s'][k]:9.4f}" if k in row['stages_s'] else f"{'-':>9s}" for k in STAGES), flush=True)
                if row.get("detail_s"):
                    print(" " * 37 + ", ".join(f"{k} {v:.4f}" for k, v in row["detail_s"].items()), flush=True)
    result = {"config": asdict(cfg), "torch": torch.__version__, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
              "load_avg": os.getloadavg(), "rows": rows, "cpu_build": _cpu_build(),
              "device_name": torch.cuda.get_device_name(0) if cfg.device.startswith("cuda") else "cpu"}
    path = REPO / "bench" / "results" / f"train_step_{cfg.name}.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    print(f"wrote {path}")
    if cfg.docs:
        write_docs(result, path, marker=cfg.docs_marker)
    return result


def format_table(result: dict) -> str:
    """Markdown: seconds per iteration per variant with the per-stage split, one line per configuration."""
    lines = ["| image | Gaussians | variant | s/iter | " + " | ".join(STAGES) + " |",
             "|---|---:|---|---:|" + "---:|" * len(STAGES)]
    for r in result["rows"]:
        st = r.get("stages_s", {})
        lines.append(f"| {r['width']}×{r['height']} | {r['n']:,} | {_variant(r)} | {r['median_s']:.3f} | "
                     + " | ".join(f"{st[k]:.3f}" if k in st else "–" for k in STAGES) + " |")
    by_config: dict[tuple, dict[str, float]] = {}
    for r in result["rows"]:
        by_config.setdefault((r["width"], r["height"], r["n"]), {})[r.get("variant", "")] = r["median_s"]
    for ref, new in (("baseline", "today"), ("today", "frozen")):
        ratios = [f"{w}×{h}/{n // 1000}k {v[ref] / v[new]:.2f}×" for (w, h, n), v in by_config.items()
                  if ref in v and new in v]
        if ratios:
            lines += ["", f"`{new}` against `{ref}` (seconds per iteration, {ref} / {new}): " + ", ".join(ratios) + "."]
    detailed = [r for r in result["rows"] if r.get("detail_s")]
    if detailed:
        keys = sorted({k for r in detailed for k in r["detail_s"]})
        lines += ["", "Inside the stages (seconds; loss terms are their forward, `backward_rest` the backward "
                  "without compositing and projection, i.e. the loss terms' gradients):", "",
                  "| image | Gaussians | variant | " + " | ".join(k.replace("_", " ") for k in keys) + " |",
                  "|---|---:|---|" + "---:|" * len(keys)]
        for r in detailed:
            lines.append(f"| {r['width']}×{r['height']} | {r['n']:,} | {r['variant']} | "
                         + " | ".join(f"{r['detail_s'].get(k, 0.0):.4f}" for k in keys) + " |")
    return "\n".join(lines)


def _variant(row: dict) -> str:
    """A row's variant as the table shows it (rows written before variants: their Adam)."""
    adam, kernels = row.get("adam", "torch"), row.get("loss_kernels", "torch")
    if "variant" not in row:
        return f"Adam {adam}"
    old = row.get("composite_kernels", "today")
    return f"{row['variant']} ({adam} Adam, {kernels} loss kernels" + ("" if old.startswith("today") else
                                                                      f", compositing of {old}") + ")"


def write_docs(result: dict, path: Path, doc: Path = REPO / "docs" / "training.md", marker: str = "train-step") -> None:
    """Put the table between the ``marker`` markers of docs/training.md."""
    load = ", ".join(f"{x:.1f}" for x in result["load_avg"])
    body = (f"From [{path.relative_to(REPO)}](../{path.relative_to(REPO)}) ({result['threads']} torch threads, "
            f"load average {load} when it ended; medians of {result['config']['iters']} iterations):\n\n"
            + format_table(result))
    replace_block(doc, marker, body)
    print(f"wrote the table into {doc}")


if __name__ == "__main__":
    import tyro

    main(tyro.cli(StepBench))
