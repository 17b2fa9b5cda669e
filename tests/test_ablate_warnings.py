"""`splat ablate` loads the scene once per row: what it says of the scene is said once per process."""

from __future__ import annotations

import json

from cues_synth import make_room_scene
from geocues.cue_io import write_cues_ply
from test_ablate import TRAIN_ARGS, write_gt
from test_train import surface_cues


def test_a_scene_warning_is_said_once_for_all_rows(tmp_path, caplog):
    """The training's sentences about the scene (field of view, photos SfM left out, unit, normal axes)
    came once per row: an ablation of 8 rows x 3 seeds said each 24 times. Rows run one after another in
    one process say each once (worker processes once each)."""
    from evaluation.mesh_metrics import MeshMetricsConfig
    from splat.ablate import AblateConfig, run

    root = make_room_scene(tmp_path / "room", n_views=16, w=64, h=48)
    meta = json.loads((root / "scene.json").read_text())
    (root / "scene.json").write_text(json.dumps({**meta, "sfm_registered": {"images": 16, "photos": 40}}))
    write_gt(root)
    write_cues_ply(tmp_path / "cues" / "cues.ply", surface_cues(root, n_plane=1500))
    cfg = AblateConfig(rows=("full", "no-cues"), iters=10, checkpoints=(1.0,), metrics=MeshMetricsConfig(n_samples=5_000))
    with caplog.at_level("WARNING"):
        run(cfg, root, tmp_path / "cues", tmp_path / "out", train_args=TRAIN_ARGS)
    assert (tmp_path / "out" / "rows" / "no-cues_s0" / "train" / "report.json").is_file()  # both rows trained
    said = [r for r in caplog.records if r.name == "splat.train_setup" and "put only 16 of the 40" in r.getMessage()]
    assert len(said) == 1, caplog.text
