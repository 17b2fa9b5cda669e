"""Cue PLY and lines3d.npz: round trips, standard readers, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from geocues.cue_io import CueCloud, read_cues_ply, read_lines_npz, write_cues_ply, write_lines_npz
from geocues.types import CueType


def _cloud(n: int = 50, seed: int = 0) -> CueCloud:
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return CueCloud(rng.uniform(-3, 3, (n, 3)), rng.integers(0, 256, (n, 3)), nrm,
                    rng.integers(0, 3, n), rng.random(n))


class TestCuePly:
    def test_roundtrip(self, tmp_path):
        c = _cloud()
        write_cues_ply(tmp_path / "c.ply", c)
        r = read_cues_ply(tmp_path / "c.ply")
        np.testing.assert_allclose(r.xyz, c.xyz, atol=1e-6)  # float32 on disk
        np.testing.assert_array_equal(r.rgb, c.rgb)
        np.testing.assert_allclose(r.normal, c.normal, atol=1e-7)
        np.testing.assert_array_equal(r.cue_type, c.cue_type)
        np.testing.assert_allclose(r.confidence, c.confidence, atol=1e-7)
        assert not list(tmp_path.glob(".c.*")), "temporary file left behind"

    def test_open3d_reads_it(self, tmp_path):
        import open3d as o3d

        c = _cloud()
        write_cues_ply(tmp_path / "c.ply", c)
        t = o3d.t.io.read_point_cloud(str(tmp_path / "c.ply"))
        np.testing.assert_allclose(t.point.positions.numpy(), c.xyz, atol=1e-6)
        np.testing.assert_array_equal(t.point.cue_type.numpy().ravel(), c.cue_type)
        np.testing.assert_allclose(t.point.confidence.numpy().ravel(), c.confidence, atol=1e-7)
        legacy = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
        np.testing.assert_allclose(np.asarray(legacy.colors) * 255, c.rgb, atol=1e-3)

    def test_reads_ascii_ply_of_other_tools(self, tmp_path):
        import open3d as o3d

        xyz = np.random.default_rng(1).random((20, 3))
        pcd = o3d.geometry.PointCloud(points=o3d.utility.Vector3dVector(xyz))
        o3d.io.write_point_cloud(str(tmp_path / "a.ply"), pcd, write_ascii=True)
        r = read_cues_ply(tmp_path / "a.ply")
        np.testing.assert_allclose(r.xyz, xyz, atol=1e-5)
        assert np.all(r.cue_type == CueType.SFM) and np.all(r.confidence == 1.0)

    def test_empty(self, tmp_path):
        write_cues_ply(tmp_path / "e.ply", CueCloud.empty())
        assert len(read_cues_ply(tmp_path / "e.ply")) == 0

    def test_bad_input(self, tmp_path):
        c = _cloud(3)
        c.xyz[0, 0] = np.nan
        with pytest.raises(ValueError, match="non-finite"):
            write_cues_ply(tmp_path / "bad.ply", c)
        with pytest.raises(FileNotFoundError, match="missing.ply"):
            read_cues_ply(tmp_path / "missing.ply")
        (tmp_path / "junk.ply").write_bytes(b"not a ply\n")
        with pytest.raises(ValueError, match="not a PLY"):
            read_cues_ply(tmp_path / "junk.ply")
        with pytest.raises(ValueError, match=r"expected \(2, 3\)"):
            CueCloud.make(np.zeros((2, 3)), np.zeros((3, 3)), CueType.LINE)

    def test_counts_and_concat(self):
        a = CueCloud.make(np.zeros((2, 3)), np.ones((2, 3)), CueType.LINE)
        b = CueCloud.make(np.zeros((5, 3)), np.zeros((5, 3), np.uint8), CueType.PLANE, confidence=0.5)
        c = CueCloud.concat([a, b])
        assert c.counts() == {"SFM": 0, "LINE": 2, "PLANE": 5}
        assert np.all(c.rgb[:2] == 255) and np.all(c.of_type(CueType.PLANE).confidence == 0.5)


class TestLinesNpz:
    def test_roundtrip_ragged_views(self, tmp_path):
        segs = np.random.default_rng(0).random((3, 2, 3))
        views = [np.array([0, 1, 2]), np.array([4]), np.array([1, 5, 6, 7])]
        write_lines_npz(tmp_path / "l.npz", segs, [3, 1, 4], views, np.full((3, 3), 0.5),
                        points=np.zeros((4, 3)), point_colors=np.ones((4, 3)), point_line=[0, 0, 1, 2])
        z = read_lines_npz(tmp_path / "l.npz")
        np.testing.assert_allclose(z["segments"], segs)
        assert [v.tolist() for v in z["views"]] == [v.tolist() for v in views]
        assert z["colors"].dtype == np.uint8 and np.all(z["colors"] == 128)
        assert z["point_line"].tolist() == [0, 0, 1, 2] and np.all(z["point_colors"] == 255)
        assert (tmp_path / "l.npz").is_file() and not (tmp_path / "l.npz.npz").exists()

    def test_empty_and_mismatch(self, tmp_path):
        write_lines_npz(tmp_path / "e.npz", np.zeros((0, 2, 3)), [], [], np.zeros((0, 3)))
        z = read_lines_npz(tmp_path / "e.npz")
        assert z["segments"].shape == (0, 2, 3) and z["views"] == []
        with pytest.raises(ValueError, match="2 segments"):
            write_lines_npz(tmp_path / "m.npz", np.zeros((2, 2, 3)), [1], [np.array([0])], np.zeros((2, 3)))
