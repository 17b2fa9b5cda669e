"""Merging two ablations of one setup (an ablation finished over several sessions or machines)."""

import copy

import pytest

from evaluation.ablation_report import merge_summaries, row_stats


def _run(seed, cl1, key="k"):
    final = {"chamfer_l1": cl1, "f_score": 0.7, "normal_consistency": 0.8, "psnr": 30.0}
    return {"seed": seed, "key": key, "curve": [final | {"step": 10}], "final": final, "train_s": 10.0 + seed}


def _summary(rows):
    return {"scene": "/a/scene", "scene_label": "room", "cues": "/a/cues", "train_args": ["--downscale", "2"],
            "config": {"rows": [r for r, _ in rows], "iters": 30, "seeds": 1, "jobs": 1, "gt": None,
                       "gt_depth": None, "gt_depth_png_scale": 1000.0, "checkpoints": [1.0], "metrics": {},
                       "floor": True},
            "floor": {"row": "floor", "status": "done", "key": "f1", "final": {"chamfer_l1": 0.01}},
            "rows": [{"row": r, "label": r} | (row_stats(runs) if runs else {"status": "pending"})
                     for r, runs in rows]}


def test_finished_rows_of_the_earlier_ablation_fill_the_pending_ones():
    old = _summary([("full", [_run(0, 0.05)]), ("no-cues", [_run(0, 0.08)]), ("mv", [_run(0, 0.04)])])
    new = _summary([("full", [_run(1, 0.07)]), ("no-cues", []), ("no-ld", [_run(0, 0.06)])])
    merged = merge_summaries(old, new)
    rows = {r["row"]: r for r in merged["rows"]}
    assert set(rows) == {"full", "no-cues", "mv", "no-ld"}
    assert rows["no-cues"]["status"] == "done" and rows["no-cues"]["mean"]["chamfer_l1"] == pytest.approx(0.08)
    # seeds of both: the mean is over seeds 0 and 1
    assert rows["full"]["n_seeds"] == 2 and [r["seed"] for r in rows["full"]["runs"]] == [0, 1]
    assert rows["full"]["mean"]["chamfer_l1"] == pytest.approx(0.06)
    assert rows["full"]["std"]["chamfer_l1"] == pytest.approx(0.01)
    assert rows["mv"]["mean"]["chamfer_l1"] == pytest.approx(0.04)
    # the earlier ablation's order first, rows only the new one ran after them
    assert [r["row"] for r in merged["rows"]] == ["full", "no-cues", "mv", "no-ld"]


def test_a_run_finished_in_both_is_taken_from_the_new_ablation():
    old = _summary([("full", [_run(0, 0.05, key="old")])])
    new = _summary([("full", [_run(0, 0.04, key="new")])])
    row = merge_summaries(old, new)["rows"][0]
    assert row["n_seeds"] == 1 and row["runs"][0]["key"] == "new"
    assert row["mean"]["chamfer_l1"] == pytest.approx(0.04)


@pytest.mark.parametrize("change, named", [
    (lambda s: s.update(train_args=["--downscale", "1"]), "train_args"),
    (lambda s: s["config"].update(iters=60), "config.iters"),
    (lambda s: s["floor"].update(key="f2"), "floor"),
    (lambda s: s.update(scene_label="other"), "scene_label"),
])
def test_ablations_of_another_setup_are_refused(change, named):
    old = _summary([("full", [_run(0, 0.05)])])
    new = copy.deepcopy(old)
    change(new)
    with pytest.raises(ValueError, match=named):
        merge_summaries(old, new)
