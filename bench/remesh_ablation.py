"""Mesh every finished row of an ablation again with other TSDF settings — no training.

Meshing happens after training, so the rendered depth that is fused (median or expected) and the
TSDF weight threshold can be compared on the Gaussians every row already trained. For each finished
row (OUT/rows/<row>_s<seed>/train) and each variant this runs what `splat mesh` runs, scores the mesh
with the ablation's own metrics, and fuses the exact-depth floor with the same weight threshold (the
floor is exact depth: the rendered-depth choice does not apply to it). Variants are named
``<depth>_w<threshold>[_c<views>][_n<neighbours>][_s<spread>][_t<steps>]`` (``_c2``: fuse only rendered depths that 2 neighbouring
renders agree with, ``--tsdf.consistent-views 2``; ``_n16``: of 16 neighbouring views instead of 4,
``--tsdf.consistency-neighbours 16``; ``_s0.02``: only pixels whose expected and median
depths agree within 2 %, ``--tsdf.max-depth-spread 0.02``; ``_t30``: 30 Taubin smoothing steps on the
trained meshes and the floor alike, ``--tsdf.smooth-iters 30``); ``median_w3`` is what `splat train` fused before
``expected`` became the default (checked: it reproduces each row's score.json).

    python bench/remesh_ablation.py outputs/ablation_textured_s0 --name textured_s0 \
        [--variants median_w3 expected_w3 median_w1 expected_w1] [--rows full no-cues]

Writes ``bench/results/remesh_<name>.json`` and prints one table per variant.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import tyro

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.doc_markers import replace_block  # noqa: E402
from evaluation.mesh_metrics import MeshMetricsConfig  # noqa: E402
from geocues.atomic import atomic_path  # noqa: E402
from splat.ablate import score_mesh  # noqa: E402
from splat.floor import find_gt_depth_dir, fuse_floor  # noqa: E402
from splat.mesh import TSDFConfig  # noqa: E402
from splat.mesh_run import MeshRunConfig  # noqa: E402
from splat.mesh_run import run as mesh_run  # noqa: E402

SHOW = ("chamfer_l1", "f_score", "normal_consistency", "completeness", "accuracy")


@dataclass
class Remesh:
    ablation: tyro.conf.Positional[Path]
    """an `splat ablate` output folder (ablation.json and rows/)."""
    name: str
    """result name: bench/results/remesh_NAME.json."""
    variants: tuple[str, ...] = ("median_w3", "expected_w3", "median_w1", "expected_w1")
    rows: tuple[str, ...] = ()
    """rows to re-mesh (default: every finished row)."""
    label: str | None = None
    """the scene's name in the tables (default: an earlier run of this name's, else the ablation's label)."""


def parse_variant(name: str) -> tuple[str, float, int | None, float | None, int, int]:
    """``<depth>_w<threshold>[_c<views>][_n<neighbours>][_s<spread>][_t<steps>]`` -> (depth, weight threshold,
    consistent_views or None, max_depth_spread or None, Taubin smoothing steps, consistency_neighbours)."""
    depth, *parts = name.split("_")
    opts = {p[0]: p[1:] for p in parts if p}
    if not parts or set(opts) - set("wcnst") or "w" not in opts:
        raise ValueError(f"variant {name!r} is not <depth>_w<threshold>[_c<views>][_n<neighbours>][_s<spread>][_t<steps>]")
    return (depth, float(opts["w"]), int(opts["c"]) if "c" in opts else None,
            float(opts["s"]) if "s" in opts else None, int(opts.get("t", 0)), int(opts.get("n", 4)))


def main(cfg: Remesh) -> dict:
    abl = json.loads((cfg.ablation / "ablation.json").read_text())
    scene = Path(abl["scene"])
    metrics = MeshMetricsConfig(**abl["config"]["metrics"])
    gt = Path(abl["config"]["gt"]) if abl["config"].get("gt") else None
    work = cfg.ablation / "remesh"
    runs = sorted(p for p in (cfg.ablation / "rows").glob("*_s*/train") if (p / "report.json").is_file()
                  and not p.parent.name.endswith(".outdated"))
    if cfg.rows:
        runs = [p for p in runs if p.parent.name.rsplit("_s", 1)[0] in cfg.rows]
    try:  # every name checked before the first (minutes-long) variant runs
        parsed = {variant: parse_variant(variant) for variant in cfg.variants}
    except ValueError as exc:
        raise SystemExit(f"remesh_ablation: {exc}") from None
    path = REPO / "bench" / "results" / f"remesh_{cfg.name}.json"
    earlier = json.loads(path.read_text()) if path.is_file() else {}
    done = earlier.get("variants", {})  # a re-run scores only what is new
    label = cfg.label or earlier.get("scene_label") or abl.get("scene_label")
    result = {"ablation": str(cfg.ablation), "scene": str(scene), "scene_label": label, "variants": {}}
    base_cfg = json.loads((runs[0] / "report.json").read_text())["config"] if runs else {}
    folder = find_gt_depth_dir(scene, abl["config"].get("gt_depth"))

    def save() -> dict:  # after every variant: a kill keeps the variants already scored
        variants = dict(result["variants"])
        for variant, rows in done.items():  # earlier variants of this name stay in its file
            variants.setdefault(variant, rows)
        merged = {**result, "variants": variants}
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(merged, indent=2))
        return merged

    for variant, (depth, w, consistent, spread, smooth, neighbours) in parsed.items():
        rows = dict(done.get(variant, {}))  # rows of an earlier run of this name stay
        tsdf = replace(TSDFConfig(**base_cfg.get("tsdf", {})), depth=depth, weight_threshold=w,
                       consistent_views=consistent, max_depth_spread=spread, smooth_iters=smooth,
                       consistency_neighbours=neighbours)
        floor_name = f"floor_w{w:g}" + (f"_t{smooth}" if smooth else "") + ".ply"
        if folder is not None and not ("floor" in rows and (work / floor_name).is_file()):
            floor_mesh = fuse_floor(scene, work / floor_name, gt_depth=folder,
                                    downscale=base_cfg.get("downscale", 1.0), test_every=base_cfg.get("test_every", 8),
                                    mesh_every=base_cfg.get("mesh_every", 1), tsdf=tsdf)
            rows["floor"] = score_mesh(floor_mesh, gt, scene, metrics)
        for run_dir in runs:
            row = run_dir.parent.name
            if row in rows and (work / row / f"{variant}.ply").is_file():
                continue
            t0 = time.perf_counter()
            out = mesh_run(MeshRunConfig(tsdf=tsdf), run_dir, work / row / f"{variant}.ply", overwrite=True)
            rows[row] = score_mesh(out, gt, scene, metrics) | {"mesh_s": time.perf_counter() - t0}
            print(variant, row, {k: round(rows[row][k], 4) for k in SHOW}, flush=True)
        result["variants"][variant] = rows
        save()
    result = save()
    print(format_table(result))
    print(f"wrote {path}")
    write_docs()
    return result


def write_docs(doc: Path = REPO / "docs" / "meshing.md") -> None:
    """Put the table of every bench/results/remesh_*.json between the remesh-summary markers."""
    parts = []
    for path in sorted((REPO / "bench" / "results").glob("remesh_*.json")):
        result = json.loads(path.read_text())
        parts.append(f"**{result.get('scene_label') or result['scene']}** "
                     f"([{path.relative_to(REPO)}](../{path.relative_to(REPO)})), C-L1 in cm / F@5cm / NC:\n\n"
                     + format_table(result))
    replace_block(doc, "remesh-summary", "\n\n".join(parts) if parts else "(no results yet)")


def format_table(result: dict) -> str:
    """Markdown: one line per row, C-L1 / F / NC per variant."""
    variants = list(result["variants"])
    rows = list(dict.fromkeys(r for v in variants for r in result["variants"][v]))
    head = "| row | " + " | ".join(f"`{v}`" for v in variants) + " |"
    lines = [head, "|---" * (len(variants) + 1) + "|"]
    for r in rows:
        cells = []
        for v in variants:
            m = result["variants"][v].get(r)
            cells.append(f"{100 * m['chamfer_l1']:.2f} / {m['f_score']:.3f} / {m['normal_consistency']:.3f}"
                         if m else "–")
        lines.append(f"| {r} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main(tyro.cli(Remesh))
