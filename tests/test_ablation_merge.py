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


def test_floors_fused_from_other_paths_with_the_same_settings_share_a_table():
    """The floor's key holds its exact-depth folder (another machine: another path); its ``setup`` does not."""
    old = _summary([("full", [_run(0, 0.05)])])
    new = copy.deepcopy(old)
    old["floor"].update(key="on-machine-a", setup="s1")
    new["floor"].update(key="on-machine-b", setup="s1")
    assert merge_summaries(old, new)["floor"]["key"] == "on-machine-b"
    new["floor"]["setup"] = "s2"
    with pytest.raises(ValueError, match="floor"):
        merge_summaries(old, new)


@pytest.mark.parametrize("old_keys, new_keys, kept", [
    (["a"], ["a"], ["a"]),
    (["b", "a"], ["a"], ["a", "b"]),  # a key of an earlier key rule shared: the same training
    (["a"], ["c"], None),             # a default of `splat train` changed between the two: refused
])
def test_ablations_trained_with_other_defaults_are_refused(old_keys, new_keys, kept):
    old = _summary([("full", [_run(0, 0.05)])]) | {"train_keys": old_keys}
    new = _summary([("full", [_run(1, 0.07)])]) | {"train_keys": new_keys}
    if kept is None:
        with pytest.raises(ValueError, match="training defaults"):
            merge_summaries(old, new)
    else:
        merged = merge_summaries(old, new)
        assert merged["rows"][0]["n_seeds"] == 2 and merged["train_keys"] == kept


@pytest.mark.parametrize("args, merges", [
    ([], False),  # neither says the budget: before train_keys the default was no limit, now "auto"
    (["--strategy.max-gaussians", "100000"], True),
    (["--strategy.max_gaussians=0"], True),
])
@pytest.mark.parametrize("keys_on", ["old", "new"])
def test_a_summary_from_before_train_keys_shares_a_table_only_with_a_budget_set(args, merges, keys_on):
    """An ablation written before summaries kept ``train_keys``: a budget set in the shared options is
    known to be the same; with none set the default it trained under is not known. The merged summary
    keeps no keys (they would claim the other side's rows)."""
    old = _summary([("full", [_run(0, 0.05)])]) | {"train_args": args}
    new = _summary([("full", [_run(1, 0.07)])]) | {"train_args": args}
    (old if keys_on == "old" else new)["train_keys"] = ["a"]
    if merges:
        merged = merge_summaries(old, new)
        assert merged["rows"][0]["n_seeds"] == 2 and "train_keys" not in merged
    else:
        with pytest.raises(ValueError, match="Gaussian budget"):
            merge_summaries(old, new)


def test_summaries_both_without_train_keys_compare_their_options_only():
    old, new = _summary([("full", [_run(0, 0.05)])]), _summary([("full", [_run(1, 0.07)])])
    assert merge_summaries(old, new)["rows"][0]["n_seeds"] == 2


def test_the_report_names_what_the_figure_draws_and_only_rows_it_holds(tmp_path):
    """report.md: the floor is the dotted line (the figure draws it so; `no-cues` rows are the dashed
    ones), the paper's C-L1 in cm as ours, no note on rows the table lacks, and no figure of empty
    panels when no row has finished."""
    from evaluation.ablation_report import write_reports

    done = _summary([("full", [_run(0, 0.05)]), ("no-cues", [_run(0, 0.08)])])
    done["rows"][0]["paper"] = (0.040, 0.78, 0.86)
    done["floor"]["final"] = _run(0, 0.01)["final"]
    for r in done["rows"]:
        r["runs"][0]["curve"][0]["train_s"] = 10.0
    write_reports(done, tmp_path / "a")
    text = (tmp_path / "a" / "report.md").read_text()
    assert "dotted black line is the floor" in text and "dashed line is the floor" not in text
    assert "| `full` full | 4.0 / 0.780 / 0.860 | 5.00" in text and "paper C-L1 (cm) / F / NC" in text
    assert "no-cues-long" not in text and "Δ: against `full`" in text
    assert (tmp_path / "a" / "accuracy_vs_time.png").stat().st_size > 0

    na = _summary([("no-ld", []), ("paper", [])])
    na["floor"]["final"] = _run(0, 0.01)["final"]
    for r in na["rows"]:
        r.update(status="n/a", reason="no depth priors")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "accuracy_vs_time.png").write_bytes(b"an earlier plot")
    write_reports(na, tmp_path / "b")
    text = (tmp_path / "b" / "report.md").read_text()
    assert "No row has finished" in text and "accuracy_vs_time.png" not in text
    assert "Δ: against `full`" not in text
    assert not (tmp_path / "b" / "accuracy_vs_time.png").exists()


def test_writing_a_report_leaves_the_users_matplotlib_backend_alone(tmp_path):
    """From a notebook: the reports switched the whole process to Agg (inline figures stopped showing)."""
    import matplotlib

    from evaluation.ablation_report import write_reports

    summary = _summary([("full", [_run(0, 0.05)])])
    summary["floor"]["final"] = _run(0, 0.01)["final"]
    summary["rows"][0]["runs"][0]["curve"][0]["train_s"] = 10.0
    before = matplotlib.get_backend()
    matplotlib.use("svg")
    try:
        write_reports(summary, tmp_path)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)
    assert (tmp_path / "accuracy_vs_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
