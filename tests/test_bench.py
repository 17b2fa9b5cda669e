"""`splat bench`: the benchmark room's geometry, and a tiny end-to-end run through the CLI."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cli.splat_cli import main
from splat.bench import FURNITURE, ROOM, bench_camera, box_triangles, room_triangles, surface_gaussians


def _bench_script(name: str):
    """bench/NAME.py imported as a module (bench/ is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def _normals(tris: np.ndarray) -> np.ndarray:
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_box_normals_face_out_or_in():
    lo, hi = np.array([1.0, 2.0, 0.0]), np.array([2.0, 4.0, 1.5])
    centre = 0.5 * (lo + hi)
    for inward, sign in ((False, 1.0), (True, -1.0)):
        tris = box_triangles(lo, hi, inward=inward)
        away = tris.mean(1) - centre  # [12, 3] from the centre to each face
        assert (sign * (_normals(tris) * away).sum(1) > 0).all()
    assert room_triangles().shape == (12 * (1 + len(FURNITURE)), 3, 3)


def test_gaussians_lie_flat_on_the_room_surfaces():
    params = surface_gaussians(3000, sh_degree=1, seed=3)
    means = params["means"].double().numpy()
    # every mean lies on one of the axis-aligned faces of the room or of a furniture box
    boxes = [((0.0, 0.0, 0.0), ROOM)] + list(FURNITURE)
    on_face = np.zeros(len(means), bool)
    normal_ok = np.zeros(len(means), bool)
    q = params["quats"].double()
    w, x, y, z = q.unbind(-1)
    # third column of R(q): the axis with the smallest scale
    axis = torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1).numpy()
    for lo, hi in boxes:
        lo, hi = np.asarray(lo), np.asarray(hi)
        inside = ((means >= lo - 1e-5) & (means <= hi + 1e-5)).all(1)
        for d in range(3):
            for plane in (lo[d], hi[d]):
                hit = inside & (np.abs(means[:, d] - plane) < 1e-5)
                on_face |= hit
                normal_ok |= hit & (np.abs(axis[:, d]) > 1 - 1e-5)
    assert on_face.all() and normal_ok.all()
    scales = params["scales"].exp()
    assert (scales[:, 2] < 0.1 * scales[:, :2].min(1).values).all()  # flat along the normal
    assert params["shN"].shape == (3000, 3, 3) and params["opacities"].shape == (3000,)


def test_camera_is_inside_the_room():
    cam = bench_camera(64, 48)
    centre = cam.center.numpy()
    assert ((centre > 0) & (centre < np.asarray(ROOM))).all()
    assert cam.K[0, 2] == 32 and cam.K[1, 2] == 24


def test_bench_cli_tiny_run(tmp_path):
    out = tmp_path / "bench.json"
    rc = main(["bench", "--sizes", "64", "48", "--counts", "2000", "--iters", "1", "--sh-degree", "1",
               "--json", str(out)])
    assert rc == 0
    result = json.loads(out.read_text())
    runs = {r["backend"]: r for r in result["runs"]}
    assert set(runs) == {"torch", "cpu"}
    for r in runs.values():
        assert r["status"] == "ok", r["status"]
        assert r["seconds_per_iter"] > 0 and len(r["times"]) == 1
        assert 0 < r["n_visible"] < 2000  # the camera sees part of the room
        assert r["peak_rss_mb"] >= 0
    assert runs["torch"]["speedup_vs_torch"] == 1.0
    assert runs["cpu"]["speedup_vs_torch"] > 0
    assert runs["cpu"]["n_visible"] == runs["torch"]["n_visible"]


def test_train_step_bench_splits_the_stages_and_restores_what_it_timed():
    """bench/train_step_bench.py on a tiny problem: both variants, every stage and the split inside
    them; the library functions it wraps for the split are the originals afterwards."""
    from splat import composite_cpu, losses, project_cpu

    bench = _bench_script("train_step_bench")
    before = (composite_cpu._CompositeCPU.__dict__["forward"], project_cpu._ProjectCPU.__dict__["backward"],
              losses.rgb_loss, losses.depth_normal_consistency_loss)
    cfg = bench.StepBench(name="test", sizes=("96x72",), counts=(1500,), iters=2)
    rows = [bench.time_config(96, 72, 1500, cfg, v) for v in ("baseline", "today")]
    after = (composite_cpu._CompositeCPU.__dict__["forward"], project_cpu._ProjectCPU.__dict__["backward"],
             losses.rgb_loss, losses.depth_normal_consistency_loss)
    assert after == before
    for row in rows:
        assert set(row["stages_s"]) == set(bench.STAGES) and row["median_s"] > 0
        d = row["detail_s"]
        assert {"composite_fwd", "composite_bwd", "projection_fwd", "projection_bwd", "backward_rest",
                "loss:rgb", "loss:depth_normal_consistency", "loss:normal_prior"} <= set(d)
        assert d["composite_fwd"] + d["projection_fwd"] <= row["stages_s"]["render"] * 1.05 + 1e-3
    assert rows[0]["loss_kernels"] == "torch" and rows[1]["loss_kernels"] == "fused"
    assert "Inside the stages" in bench.format_table({"rows": rows})
    frozen = bench.time_config(96, 72, 1500, cfg, "frozen")  # the colour step of a frozen geometry
    assert frozen["stages_s"] == {} and frozen["median_s"] > 0
    assert {"composite_bwd", "projection_bwd"} <= set(frozen["detail_s"])
    assert not any(k.startswith("loss:depth") for k in frozen["detail_s"])  # L_rgb alone
    assert "`frozen` against `today`" in bench.format_table({"rows": rows + [frozen]})


def test_room_curve_table_reads_the_checkpoints_and_sums_up_the_second_half(tmp_path, monkeypatch):
    """bench/room_curve_table.py: one line per run with every checkpoint, the change from step 1500 to
    the end over the runs, and a clear stop for a run whose checkpoints differ."""
    mod = _bench_script("room_curve_table")
    monkeypatch.setattr(mod, "REPO", tmp_path)

    def write(name, fs, steps=(300, 750, 1500, 3000)):
        curve = [{"step": s, "train_s": s / 4, "psnr": 20 + s / 300, "chamfer_l1": 0.1 - f / 10,
                  "f_score": f, "normal_consistency": 0.9} for s, f in zip(steps, fs)]
        d = tmp_path / "bench" / "results" / f"ablation_{name}"
        d.mkdir(parents=True)
        (d / "ablation.json").write_text(json.dumps({"rows": [{"row": "full", "runs": [{"curve": curve}]}]}))

    write("a", (0.70, 0.80, 0.82, 0.81))
    write("b", (0.70, 0.80, 0.84, 0.86))
    text = mod.table([("room a", "a"), ("room b", "b")], "full")
    lines = text.splitlines()
    assert lines[0] == "| room | step 300 | step 750 | step 1500 | step 3000 |"
    assert lines[2].startswith("| room a | 3.00 / 0.700 / 0.900 / 21.0 (75 s) |")
    assert "over the 2 runs" in text and "F +0.005 (-0.010 to +0.020)" in text
    assert "training +375 s" in text
    write("c", (0.7, 0.8, 0.9), steps=(300, 750, 3000))
    with pytest.raises(SystemExit, match="checkpoints"):
        mod.table([("room a", "a"), ("room c", "c")], "full")
    with pytest.raises(SystemExit, match="no finished row 'room'"):
        mod.table([("room a", "a")], "room")


def test_recipe_table_reads_named_rows_and_scores_fixed_targets(tmp_path, monkeypatch):
    """bench/recipe_table.py: ``NAME:ROW`` picks a row other than `full`; a room given fixed targets is
    scored against them (ICL: 3.0 cm, 0.85, 0.85), the others against their floor; the paper's margins
    over `no-cues`."""
    mod = _bench_script("recipe_table")
    monkeypatch.setattr(mod, "RESULTS", tmp_path)

    def metrics(c, f, n, psnr=30.0, train_s=100.0):
        return {"chamfer_l1": c, "f_score": f, "normal_consistency": n, "psnr": psnr, "train_s": train_s}

    def write(name, rows, floor=(0.02, 0.95, 0.97), floors=None):
        d = tmp_path / f"ablation_{name}"
        d.mkdir()
        data = {"floor": {"final": metrics(*floor)}, "floors": floors or {},
                "rows": [{"row": r, "status": "done", "n_seeds": 1, "mean": m,
                          "runs": [{"curve": [{"step": 300, "psnr": 20.0}]}]} for r, m in rows.items()]}
        (d / "ablation.json").write_text(json.dumps(data))

    write("old", {"full": metrics(0.048, 0.71, 0.73), "no-cues": metrics(0.07, 0.66, 0.75)})
    write("new", {"mvs": metrics(0.029, 0.87, 0.86, train_s=400.0)})
    text = mod.table([("ICL", "old", "new:mvs", "old")], "full", "mvs", {"ICL": (3.0, 0.85, 0.85)})
    row = text.splitlines()[2]
    assert row.startswith("| ICL | 4.80 / 0.710 / 0.730 / 30.0 | **2.90 / 0.870 / 0.860 / 30.0** |")
    assert "all of ≤ 3 cm, ≥ 0.85, ≥ 0.85" in row and "yes (-59 %, +0.21, +0.110)" in row and "100 → 400" in row
    write("worse", {"mvs": metrics(0.031, 0.87, 0.84)})
    row = mod.table([("ICL", "old", "worse:mvs")], "full", "mvs", {"ICL": (3.0, 0.85, 0.85)}).splitlines()[2]
    assert "F of ≤ 3 cm" in row and "misses C-L1 3.10 > 3 cm, NC 0.840 < 0.85" in row
    row = mod.table([("room", "old", "worse:mvs")], "full", "mvs").splitlines()[2]  # against its floor
    assert "misses C-L1 1.55×" in row
    # a row whose preset meshes otherwise is scored against the floor of its own meshing
    write("own", {"mvs": metrics(0.031, 0.87, 0.84)}, floors={"mvs": {"status": "done", "final": metrics(0.0155, 0.9, 0.9)}})
    row = mod.table([("room", "old", "own:mvs")], "full", "mvs").splitlines()[2]
    assert "| 1.55 / 0.900 / 0.900 |" in row and "misses C-L1 2.00×" in row
    summary = _bench_script("ablation_summary").scene_table(json.loads((tmp_path / "ablation_own" / "ablation.json").read_text())
                                                            | {"scene_label": "room", "train_args": [],
                                                               "config": {"iters": 30, "seeds": 1}})
    assert "| floor through `mvs`'s meshing | 1.55 |" in summary and "| 2.00 |" in summary


def test_collect_with_a_label_names_the_scene_in_json_report_and_merge(tmp_path, monkeypatch):
    """bench/ablation_summary.py ``--collect OUT NAME --label TEXT``: the collected JSON and report.md
    carry the label (not the run's), and a second run collected under the same label merges into it."""
    from tests.test_ablation_merge import _run, _summary

    mod = _bench_script("ablation_summary")
    monkeypatch.setattr(mod, "RESULTS", tmp_path / "results")

    def run_out(name, rows):
        out = tmp_path / name
        out.mkdir()
        summary = _summary(rows)
        summary["floor"]["final"] = _run(0, 0.01)["final"]
        for r in summary["rows"]:
            for run in r["runs"]:
                run["curve"][0]["train_s"] = run["train_s"]
        (out / "ablation.json").write_text(json.dumps(summary))
        return out

    dst = mod.collect(run_out("a", [("full", [_run(0, 0.05)])]), "x", label="room, seed 0")
    data = json.loads((dst / "ablation.json").read_text())
    assert data["scene_label"] == data["config"]["scene_label"] == "room, seed 0"
    assert (dst / "report.md").read_text().startswith("# Ablation on room, seed 0")
    assert (dst / "accuracy_vs_time.png").stat().st_size > 0
    mod.collect(run_out("b", [("full", [_run(1, 0.07)])]), "x", label="room, seed 0")
    row = json.loads((dst / "ablation.json").read_text())["rows"][0]
    assert row["n_seeds"] == 2
    with pytest.raises(SystemExit, match="scene_label"):  # without the label the run's own differs
        mod.collect(run_out("c", [("full", [_run(2, 0.07)])]), "x")
    with pytest.raises(SystemExit, match="no ablation.json"):  # not an ablation's OUT: one line, no folder made
        mod.collect(tmp_path / "missing", "y")
    assert not (tmp_path / "results" / "ablation_y").exists()


def test_mvs_cues_table_reads_the_committed_results():
    """bench/mvs_cues_table.py: one row per pair of committed ablations, four figures in each cell."""
    mod = _bench_script("mvs_cues_table")
    lines = mod.table().splitlines()
    assert len(lines) == 2 + len(mod.PAIRS)
    for line in lines[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert len(cells) == 3 and all(len(c.split(" / ")) == 4 for c in cells[1:]), line


def test_images_only_scale_table_prints_one_row_per_unit_and_seed(tmp_path, capsys):
    """bench/images_only_scale_table.py: rows in the order mapped, guess, exact, seeds from the names."""
    mod = _bench_script("images_only_scale_table")
    ev = lambda c: {"chamfer_l1": c, "f_score": 0.5, "normal_consistency": 0.8}  # noqa: E731
    res = {"variants": {v: {"m_per_unit": m, "metres_per_unit_error": m / 0.2 - 1, "median_view_depth_units": 1.7 * 0.2 / m,
                            "no-icp": ev(0.1), "icp": ev(0.05), "test_psnr": 30.0, "gaussians_init": {"SFM": 3, "PLANE": 4},
                            "train_s": 100.0} for v, m in (("mapped", 1.0), ("guess", 0.23), ("exact", 0.2))}}
    for name in ("icl_images_only_scale.json", "icl_images_only_scale_seed1.json"):
        (tmp_path / name).write_text(json.dumps(res))
    assert mod.main(sorted(str(p) for p in tmp_path.glob("*.json"))) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 + 6 and "as mapped" in lines[2] and "(+400 %)" in lines[2] and "(+15 %)" in lines[3]
    assert "10.00 / 0.500 / 0.800 | 5.00 / 0.500 / 0.800" in lines[4] and "seed 1" in lines[7] and "| 7 |" in lines[4]
    doc = tmp_path / "doc.md"
    doc.write_text("a\n<!-- images-only-scale -->\nold\n<!-- /images-only-scale -->\nb\n")
    from bench.doc_markers import replace_block  # the scripts' one marker-block writer

    replace_block(doc, "images-only-scale", "new")
    assert doc.read_text() == "a\n<!-- images-only-scale -->\nnew\n<!-- /images-only-scale -->\nb\n"


def test_readme_demo_figures_are_generated_from_the_committed_run():
    """README.md's main-job table and time line are what bench/ablation_summary.py --demo makes of
    the run kept in bench/results/demo/ (ablation.json, timings.json): no figure there is typed."""
    mod = _bench_script("ablation_summary")
    repo = Path(__file__).resolve().parents[1]
    keep = repo / "bench" / "results" / "demo"
    readme = (repo / "README.md").read_text()
    assert mod.scene_table(json.loads((keep / "ablation.json").read_text())) in readme
    assert mod.demo_time_line(json.loads((keep / "timings.json").read_text())) in readme


def test_demo_time_line_names_each_step():
    mod = _bench_script("ablation_summary")
    t = {"date": "2026-01-02", "cpus": 2, "room_made": True, "total_s": 287.4,
         "steps_s": {"room": 36.2, "cues": 25.0, "cue_scoring": 4.1, "ablation": 218.6, "final_scoring": 3.5}}
    line = mod.demo_time_line(t)
    assert line.startswith("Time: **4 min 47 s** wall on 2 cores (2026-01-02")
    for part in ("the room 36 s to render", "cues 25 s", "scoring 4 s", "the reports 219 s", "final scoring 4 s"):
        assert part in line, part
    assert "the room already made (0 s)" in mod.demo_time_line(t | {"room_made": False, "steps_s": t["steps_s"] | {"room": 0.2}})


def test_budget_table_in_the_docs_is_generated_from_the_committed_results():
    """docs/training.md's "Budget" table is what bench/budget_summary.py makes of bench/results/budget_*.json."""
    mod = _bench_script("budget_summary")
    doc = (Path(__file__).resolve().parents[1] / "docs" / "training.md").read_text()
    assert f"<!-- budget-table -->\n{mod.table()}\n<!-- /budget-table -->" in doc


def test_budget_rows_give_mean_and_spread_over_seeds(tmp_path):
    """bench/budget_summary.py: an ablation's `full` row of two seeds is one budget, mean ± population std."""
    mod = _bench_script("budget_summary")
    runs = []
    for seed, cl1, psnr in ((0, 0.10, 20.0), (1, 0.12, 22.0)):
        train = tmp_path / "rows" / f"full_s{seed}" / "train"
        train.mkdir(parents=True)
        (train / "report.json").write_text(json.dumps({
            "config": {"seed": seed, "downscale": 2.0, "strategy": {"max_gaussians": "auto"}}, "gaussian_budget": 100_000,
            "gaussians_final": {"SFM": 60_000, "PLANE": 39_000}, "accuracy_vs_time": [{"step": 30, "train_s": 50.0 + seed, "psnr": psnr}]}))
        (train / "cameras.json").write_text(json.dumps([{"width": 320, "height": 240}]))  # the photos' own size
        runs.append({"seed": seed, "final": {"chamfer_l1": cl1, "f_score": 0.5, "normal_consistency": 0.8}})
    (tmp_path / "ablation.json").write_text(json.dumps({
        "rows": [{"row": "full", "runs": runs}],
        "floor": {"final": {"chamfer_l1": 0.05, "f_score": 0.7, "normal_consistency": 0.9}}}))
    row = mod._row(tmp_path)
    assert row["n_seeds"] == 2 and row["is_default"] and row["budget"] == 100_000 and row["view_pixels"] == 160 * 120
    assert row["chamfer_l1_cm"] == pytest.approx(11.0) and row["std"]["chamfer_l1_cm"] == pytest.approx(1.0)
    lines = mod.table_lines("room", [row])
    assert lines[0] == "| room | auto, 100k | 2 | 99k | 50 | 11.00 ± 1.00 | 0.500 ± 0.000 | 0.800 ± 0.000 | 21.00 ± 1.00 |"
    assert lines[1] == "| room | floor (exact GT depth) | | | | 5.00 | 0.700 | 0.900 | |"
