"""``argus bench replay`` (bench/replay.py): the scorer, the reference surface, the launch file it plays, its errors.

Pure functions on small data, no process and no socket; the whole stack is played in test_replay_stack.py (slow).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench import replay
from bench import sequences as seqs
from bench.replay import NodeCloud
from deploy.up import load_launch
from protocol.poses import PoseAccuracy, look_at
from tests.support.recorded import SIZE, write_sequence


def plane(step_m: float = 0.01, size_m: float = 1.0, z_m: float = 0.0) -> np.ndarray:
    """Points on a square of the plane z = ``z_m``, ``step_m`` apart."""
    g = np.arange(0.0, size_m + 1e-9, step_m)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z_m)], axis=1)


def node(node_id: str, label: str, centroid: tuple[float, float, float], points: np.ndarray | None = None,
         extent: tuple[float, float, float] = (0.2, 0.2, 0.2)) -> NodeCloud:
    return NodeCloud(node_id, label, np.asarray(centroid, float), replay.box_corners(centroid, extent, 0.0), points)


class TestMapScores:
    def test_a_map_equal_to_the_reference_is_exact_and_complete(self) -> None:
        ref = plane()
        s = replay.map_scores(ref.copy(), ref)
        assert s["accuracy_mean_m"] == 0.0 and s["accuracy_median_m"] == 0.0
        assert s["completion_5cm"] == 1.0 and s["completion_10cm"] == 1.0
        assert s["map_points"] == s["reference_points"] == len(ref)

    def test_a_map_shifted_by_10_cm_is_10_cm_off_and_not_complete_at_5_cm(self) -> None:
        ref = plane()
        s = replay.map_scores(ref + [0.0, 0.0, 0.10], ref)
        assert s["accuracy_median_m"] == pytest.approx(0.10) and s["accuracy_mean_m"] == pytest.approx(0.10)
        assert s["completion_5cm"] == 0.0
        assert s["completion_10cm"] > 0.99  # exactly 10 cm away: inside 10 cm up to rounding

    def test_a_sparse_map_of_the_same_surface_is_exact_but_incomplete(self) -> None:
        ref = plane()
        sparse = plane(step_m=0.25)
        s = replay.map_scores(sparse, ref)
        assert s["accuracy_median_m"] == 0.0
        assert 0.05 < s["completion_5cm"] < 0.5 < s["completion_10cm"] <= 1.0

    def test_empty_inputs(self) -> None:
        ref = plane(step_m=0.1)
        empty = np.zeros((0, 3))
        s = replay.map_scores(empty, ref)
        assert math.isnan(s["accuracy_median_m"]) and s["completion_5cm"] == 0.0 and s["map_points"] == 0
        s = replay.map_scores(ref, empty)
        assert math.isnan(s["accuracy_mean_m"]) and math.isnan(s["completion_10cm"])

    def test_nearest_m_to_nothing_is_infinitely_far(self) -> None:
        assert np.isinf(replay.nearest_m(np.zeros((2, 3)), np.zeros((0, 3)))).all()
        assert replay.nearest_m(np.zeros((0, 3)), np.zeros((1, 3))).shape == (0,)


class TestNodes:
    def test_nodes_are_scored_by_their_own_points_else_their_box(self) -> None:
        ref = plane()
        on = node("n1", "object", (0.5, 0.5, 0.0), points=plane(0.05, 0.2) + [0.4, 0.4, 0.02])
        off = node("n2", "object", (0.5, 0.5, 0.3), points=plane(0.05, 0.2) + [0.4, 0.4, 0.3])
        boxed = node("n3", "chair", (0.5, 0.5, 0.05), extent=(0.2, 0.2, 0.1))  # corners 0 and 0.1 m above the plane
        rows, summary = replay.node_scores([on, off, boxed], ref)
        by_id = {r["node_id"]: r for r in rows}
        assert by_id["n1"]["within"] == 1.0 and by_id["n1"]["scored_by"] == "points"
        assert by_id["n2"]["within"] == 0.0 and by_id["n2"]["centroid_m"] == pytest.approx(0.3)
        assert by_id["n3"]["scored_by"] == "box" and by_id["n3"]["points"] == 9 and by_id["n3"]["within"] == 1.0
        assert summary["nodes"] == 3 and summary["nodes_scored_by_box"] == 1
        assert summary["node_points_within"] == pytest.approx(2 / 3)
        assert summary["nodes_90pct_within"] == pytest.approx(2 / 3)
        n1, n2 = len(on.points), len(off.points)  # type: ignore[arg-type]
        assert summary["node_points_within_pooled"] == pytest.approx((n1 + 9) / (n1 + n2 + 9))

    def test_no_nodes(self) -> None:
        rows, summary = replay.node_scores([], plane(0.1))
        assert rows == [] and summary["nodes"] == 0 and math.isnan(summary["node_points_within"])

    def test_duplicates_are_close_pairs_of_one_label(self) -> None:
        nodes = [node("a", "chair", (0, 0, 0)), node("b", "chair", (0.3, 0, 0)), node("c", "chair", (2, 0, 0)),
                 node("d", "table", (0.1, 0, 0))]
        pairs = replay.duplicate_pairs(nodes)
        assert [(p["a"], p["b"], p["label"]) for p in pairs] == [("a", "b", "chair")]
        assert pairs[0]["distance_m"] == pytest.approx(0.3)
        assert replay.labels_count(nodes) == {"chair": 3, "table": 1}

    def test_box_corners_turn_with_the_yaw_and_give_it_back(self) -> None:
        c = replay.box_corners((1.0, 2.0, 0.5), (0.4, 0.2, 1.0), math.pi / 2)
        assert c.shape == (8, 3)
        assert np.allclose(c.min(0), [0.9, 1.8, 0.0]) and np.allclose(c.max(0), [1.1, 2.2, 1.0])
        n = NodeCloud("n", "x", np.zeros(3), c)
        assert replay._box_yaw(n) == pytest.approx(math.pi / 2)
        assert np.allclose(replay.box_size(n), [0.4, 0.2, 1.0])
        assert np.allclose(replay.box_center(n), [1.0, 2.0, 0.5])


def labelled(node_id: str, label: str, centroid: tuple[float, float, float], n_points: int = 0,
             confidence: float = 0.8) -> NodeCloud:
    pts = np.tile(np.asarray(centroid, float), (n_points, 1)) if n_points else None
    return NodeCloud(node_id, label, np.asarray(centroid, float),
                     replay.box_corners(centroid, (0.2, 0.4, 0.6), 0.0), pts, confidence)


class TestLabels:
    def test_with_real_labels_pairs_are_counted_over_the_labelled_nodes_only(self) -> None:
        nodes = [labelled("m1", "Computer monitor", (0, 0, 0)), labelled("m2", "Computer monitor", (0.2, 0, 0)),
                 labelled("o1", "object", (0, 0.1, 0)), labelled("o2", "object", (0.1, 0.1, 0))]
        pairs, over = replay.label_duplicates(nodes)
        assert over == "labelled nodes" and [(p["a"], p["b"]) for p in pairs] == [("m1", "m2")]
        assert replay.has_labels(nodes)

    def test_class_agnostic_nodes_count_every_close_pair(self) -> None:
        nodes = [labelled("o1", "object", (0, 0, 0)), labelled("o2", "object", (0.3, 0, 0))]
        pairs, over = replay.label_duplicates(nodes)
        assert over.startswith("all nodes") and len(pairs) == 1 and not replay.has_labels(nodes)
        assert replay.label_duplicates([]) == ([], "all nodes (class-agnostic)")

    def test_node_rows_carry_label_confidence_box_and_what_they_are_judged_on(self) -> None:
        nodes = [labelled("c", "Chair", (1.0, 2.0, 0.3), n_points=4, confidence=0.65),
                 labelled("o", "object", (0.0, 0.0, 0.0), n_points=2)]
        rows, _ = replay.node_scores(nodes, np.array([[1.0, 2.0, 0.3], [0.0, 0.0, 0.0]]))
        c, o = rows
        assert c["label_confidence"] == 0.65 and c["judged_on"] == "label + geometry"
        assert c["box_center_m"] == [1.0, 2.0, 0.3] and c["box_size_m"] == [0.2, 0.4, 0.6] and c["box_yaw_deg"] == 0.0
        assert o["judged_on"] == "geometry only" and c["within"] == o["within"] == 1.0
        table = replay.node_table(list(reversed(rows)))
        assert [r["node"] for r in table] == ["c", "o"]  # labelled first
        assert table[0]["box centre (m)"] == "1.00, 2.00, 0.30" and table[0]["confidence"] == "0.65"

    def test_only_class_agnostic_rows_are_geometry_only_when_there_are_no_labels(self) -> None:
        rows, _ = replay.node_scores([labelled("o", "object", (0, 0, 0))], plane(0.1))
        assert rows[0]["judged_on"] == "geometry only"

    def test_the_notes_say_when_the_detector_saw_nothing_it_knows(self) -> None:
        res = {"replay": {"labelled_nodes": 0.0, "nodes": 3.0},
               "perception": {"segmenter": "detector", "embedder": "detector"}}
        assert "saw nothing it knows" in replay.labels_note(res)
        res["perception"] = {"segmenter": "classical", "embedder": "classical"}
        assert "class-agnostic" in replay.labels_note(res)
        res["replay"] = {"labelled_nodes": 2.0, "nodes": 3.0}
        assert "2 of 3 nodes carry a class" in replay.labels_note(res)


class TestTopDownLabels:
    def test_labelled_nodes_are_numbered_by_label_then_size(self) -> None:
        nodes = [labelled("a", "Mug", (0, 0, 0), 5), labelled("b", "Chair", (1, 0, 0), 3),
                 labelled("c", "Mug", (2, 0, 0), 50), labelled("d", "object", (3, 0, 0), 500)]
        assert [n.node_id for n in replay.numbered_nodes(nodes)] == ["b", "c", "a"]
        agnostic = [labelled("x", "object", (0, 0, 0), 1), labelled("y", "object", (1, 0, 0), 9)]
        assert [n.node_id for n in replay.numbered_nodes(agnostic)] == ["y", "x"]
        assert replay.numbered_nodes([]) == []

    def test_labels_keep_apart_and_free_ones_stay_on_their_anchor(self) -> None:
        anchors = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01], [5.0, 5.0]])
        spots = replay.spread_labels(anchors, 0.5)
        assert spots.shape == (4, 2)
        assert np.array_equal(spots[0], anchors[0]) and np.array_equal(spots[3], anchors[3])
        d = np.linalg.norm(spots[:, None] - spots[None], axis=-1)[np.triu_indices(4, 1)]
        assert d.min() >= 0.5 - 1e-9
        assert replay.spread_labels(np.zeros((0, 2)), 0.1).shape == (0, 2)

    def test_the_top_down_view_draws_labels_and_agnostic_boxes(self, tmp_path: Path) -> None:
        nodes = [labelled("a", "Mug", (0, 0, 0), 5), labelled("d", "object", (1, 0, 0), 5)]
        out = tmp_path / "v.png"
        replay.plot_top_down(out, plane(0.1), np.full((121, 3), 128, np.uint8), np.zeros((0, 3)), nodes, (2, 1), "t")
        assert out.stat().st_size > 0


class TestPerception:
    def test_the_choice_sets_segmenter_and_embedder_and_keeps_options_of_an_unchanged_backend(self) -> None:
        current = {"segmenter": "detector", "segmenter_options": {"tile_grid": 0}, "embedder": "classical",
                   "embedder_options": {"bins": 8}}
        out = replay.perception_settings(current, "detector")
        assert out == {"segmenter": "detector", "segmenter_options": {"tile_grid": 0}, "embedder": "detector"}
        assert replay.perception_settings({}, "classical") == {"segmenter": "classical", "embedder": "classical"}
        with pytest.raises(ValueError, match="one of"):
            replay.perception_settings({}, "sam2")

    def test_the_stack_and_the_in_process_mapper_get_the_same_perception(self, tmp_path: Path) -> None:
        launch, _, mapper = replay.replay_launch(replay.DEFAULT_LAUNCH, tmp_path, 1.0, None, "tcp/127.0.0.1:1",
                                                 tmp_path, perception="detector")
        m = next(p for p in launch.process if p.command == "mapper").settings
        assert m is not None and m["perception"] == mapper["perception"] == {"segmenter": "detector",
                                                                             "embedder": "detector"}
        _, _, default = replay.replay_launch(replay.DEFAULT_LAUNCH, tmp_path, 1.0, None, "tcp/127.0.0.1:1", tmp_path)
        assert default["perception"] == {"segmenter": "classical", "embedder": "classical"}

    def test_a_missing_detector_model_is_one_line_and_starts_nothing(
            self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
        import mapper.perception.detector as det

        monkeypatch.setattr(det, "bundled_model", lambda: tmp_path / "absent.tflite")
        folder = with_depth(tmp_path / "s")
        assert replay.main(["--sequence", str(folder), "--perception", "detector", "--out", str(tmp_path / "o")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--perception detector" in err[0] and "absent.tflite" in err[0]
        assert not (tmp_path / "o").exists()
        replay.check_perception(None)  # the launch file's: nothing to check here


class TestCompare:
    def test_gaps_are_relative_to_the_in_process_figures(self) -> None:
        a = {"accuracy_mean_m": 0.022, "accuracy_median_m": 0.02, "completion_5cm": 0.5, "completion_10cm": 0.6}
        b = {"accuracy_mean_m": 0.02, "accuracy_median_m": 0.02, "completion_5cm": 0.5, "completion_10cm": 0.6}
        g = replay.compare(a, b)
        assert g["gap_accuracy_mean_m"] == pytest.approx(0.1) and g["gap_max"] == pytest.approx(0.1)
        assert math.isnan(replay.compare(a, dict(b, completion_5cm=0.0))["gap_max"])
        assert math.isnan(replay.relative_gap(math.nan, 1.0))


class TestUpAxis:
    def test_upright_cameras_in_a_z_up_world(self) -> None:
        poses = [look_at([x, 0.0, 1.5], [x, 3.0, 1.0]) for x in (0.0, 1.0)]
        assert replay.up_axis(poses) == (2, 1)

    def test_opencv_cameras_at_the_origin_make_minus_y_up(self) -> None:
        assert replay.up_axis([np.eye(4)]) == (1, -1)


META = {"depth_divisor": 1000, "valid_depth_m": [0.2, 5.0], "licence": "test"}


def with_depth(folder: Path, n: int = 3, meta: dict | None = None, scale: int = 1) -> Path:
    """A recorded folder (tests.support.recorded, its images and K ``scale`` times larger) whose frames see a wall
    3 m along world y, with each frame's depth of it."""
    write_sequence(folder, n=n, meta=META if meta is None else meta)
    K = np.loadtxt(folder / "camera-intrinsics.txt")
    w, h = SIZE[0] * scale, SIZE[1] * scale
    if scale != 1:
        K[:2, :2] *= scale
        K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
        np.savetxt(folder / "camera-intrinsics.txt", K)
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)  # camera z = 1
    for i in range(n):
        stem = folder / "frames" / f"frame-{i:06d}"
        if scale != 1:
            img = cv2.imread(f"{stem}.color.png")
            cv2.imwrite(f"{stem}.color.png", cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST))
        T = np.loadtxt(f"{stem}.pose.txt")
        z = (3.0 - T[1, 3]) / (rays @ T[:3, :3].T)[..., 1]  # the ray parameter to the wall is the z-depth
        cv2.imwrite(f"{stem}.depth.png", np.round(z * 1000).astype(np.uint16))
    return folder


class TestReference:
    def test_the_tsdf_surface_lies_on_the_recorded_wall(self, tmp_path: Path) -> None:
        seq = seqs.load(with_depth(tmp_path / "s"))
        voxel = replay.reference_voxel_m(seq.frames)
        assert 0.005 <= voxel <= 0.02
        pts, cols = replay.reference_surface(seq.frames, voxel)
        assert len(pts) > 100 and cols.shape == (len(pts), 3) and cols.dtype == np.uint8
        assert np.abs(pts[:, 1] - 3.0).max() < 2 * voxel  # every surface point on the wall y = 3 m

    def test_no_valid_depth_is_no_reference(self, tmp_path: Path) -> None:
        seq = seqs.load(with_depth(tmp_path / "s"))
        for f in seq.frames:
            f.valid[:] = False
        pts, cols = replay.reference_surface(seq.frames, 0.01)
        assert pts.shape == (0, 3) and cols.shape == (0, 3)


class TestLaunch:
    def test_the_shipped_launch_file_is_a_replay_stack(self, tmp_path: Path) -> None:
        shipped = load_launch(replay.DEFAULT_LAUNCH)
        assert [p.command for p in shipped.process] == ["router", "mapper", "edge-camera"]
        launch, camera_id, mapper = replay.replay_launch(
            replay.DEFAULT_LAUNCH, tmp_path / "seq", 2.0, PoseAccuracy(0.01, 0.5), "tcp/127.0.0.1:1234",
            tmp_path / "state")
        assert launch.endpoint == "tcp/127.0.0.1:1234" and camera_id == "replay"
        assert mapper["geometry"] == {"backend": "mvs"} and mapper["workers"] == {"local": 1}
        cam = next(p for p in launch.process if p.command == "edge-camera").settings
        assert cam is not None
        assert cam["source"] == {"type": "recorded", "path": str((tmp_path / "seq").resolve()), "rate_hz": 2.0,
                                 "loop": False, "pose_sigma_trans_m": 0.01, "pose_sigma_rot_deg": 0.5}
        assert cam["publish"]["max_rate_hz"] >= 4.0
        m = next(p for p in launch.process if p.command == "mapper").settings
        assert m is not None and m["state_dir"] == str(tmp_path / "state")
        undeclared = replay.replay_launch(replay.DEFAULT_LAUNCH, tmp_path, 0.5, None, "tcp/127.0.0.1:1", tmp_path)[0]
        src = next(p for p in undeclared.process if p.command == "edge-camera").settings["source"]  # type: ignore[index]
        assert "pose_sigma_trans_m" not in src and "pose_sigma_rot_deg" not in src
        assert "world_from_recording" not in src
        W = [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 1.5], [0, 0, 0, 1]]  # a sidecar's, which the camera cannot read
        turned = replay.replay_launch(replay.DEFAULT_LAUNCH, tmp_path, 0.5, None, "tcp/127.0.0.1:1", tmp_path,
                                      world_from_recording=W)[0]
        src = next(p for p in turned.process if p.command == "edge-camera").settings["source"]  # type: ignore[index]
        assert src["world_from_recording"] == W

    def test_a_launch_file_without_a_recorded_camera_is_refused(self, tmp_path: Path) -> None:
        bad = tmp_path / "bad.toml"
        bad.write_text(replay.DEFAULT_LAUNCH.read_text().replace('type = "recorded"', 'type = "pattern"'))
        with pytest.raises(ValueError, match="recorded"):
            replay.replay_launch(bad, tmp_path, 1.0, None, "tcp/127.0.0.1:1", tmp_path)
        two = tmp_path / "two.toml"
        two.write_text(load_text_without_camera(replay.DEFAULT_LAUNCH))
        with pytest.raises(ValueError, match="one router, one mapper and one edge-camera"):
            replay.replay_launch(two, tmp_path, 1.0, None, "tcp/127.0.0.1:1", tmp_path)


def load_text_without_camera(path: Path) -> str:
    text = path.read_text()
    return text[: text.index('name = "camera"')].rsplit("[[process]]", 1)[0]


class TestErrors:
    def test_a_broken_folder_is_one_line_and_starts_nothing(self, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
        folder = with_depth(tmp_path / "s")
        (folder / "frames" / "frame-000001.pose.txt").unlink()
        assert replay.main(["--sequence", str(folder), "--out", str(tmp_path / "out")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "frame-000001.pose.txt: missing" in err[0]
        assert not (tmp_path / "out").exists()

    def test_k_under_another_name_reaches_the_camera(self, tmp_path: Path) -> None:
        folder = with_depth(tmp_path / "s", meta=dict(META, intrinsics_file="camera-intrinsics.color.txt"))
        (folder / "camera-intrinsics.txt").rename(folder / "camera-intrinsics.color.txt")
        seq = replay.load_checked(replay.ReplaySetup(sequence=folder))  # labelfusion's layout: K's own file name
        launch = replay.replay_launch(replay.DEFAULT_LAUNCH, folder, 0.5, None, "tcp/127.0.0.1:1", tmp_path,
                                      intrinsics_file=seq.meta.intrinsics_file)[0]
        src = next(p for p in launch.process if p.command == "edge-camera").settings["source"]  # type: ignore[index]
        assert src["intrinsics_file"] == "camera-intrinsics.color.txt"

    def test_undeclared_cannot_replay_a_folder_that_declares(self, tmp_path: Path) -> None:
        folder = with_depth(tmp_path / "s", meta=dict(META, pose_sigma_trans_m=0.01, pose_sigma_rot_deg=1.0))
        with pytest.raises(seqs.SequenceError, match="--undeclared"):
            replay.load_checked(replay.ReplaySetup(sequence=folder, declared=False))
        assert replay.load_checked(replay.ReplaySetup(sequence=folder)).meta.declared() == PoseAccuracy(0.01, 1.0)

    def test_frames_are_told_apart_by_their_pose(self, tmp_path: Path) -> None:
        seq = seqs.load(with_depth(tmp_path / "s", n=3))
        sent = {7: seq.frames[2].T_world_cam, 5: seq.frames[0].T_world_cam}
        assert replay.frame_index_of(sent, seq.frames) == {7: 2, 5: 0}
        assert replay.frame_index_of(sent, []) == {}


def test_pose_errors_compare_by_frame_index() -> None:
    recorded = {0: np.eye(4), 1: look_at([1.0, 0.0, 1.5], [1.0, 3.0, 1.0])}
    moved = recorded[1].copy()
    moved[:3, 3] += [0.03, 0.0, 0.04]
    pe = replay.pose_errors(recorded, {0: np.eye(4), 1: moved, 9: np.eye(4)})
    assert pe["n"] == 2 and pe["trans_cm_max"] == pytest.approx(5.0) and pe["rot_deg_max"] == pytest.approx(0.0)
    assert pe["trans_cm_median"] == pytest.approx(2.5)
    assert math.isnan(replay.pose_errors(recorded, {})["trans_cm_median"])


def test_summary_rows_say_which_bars_are_met() -> None:
    figs = {"map_points": 10.0, "reference_points": 100.0, "accuracy_mean_m": 0.02, "accuracy_median_m": 0.02,
            "completion_5cm": 0.4, "completion_10cm": 0.7, "nodes": 2.0, "node_points_within": 0.95,
            "node_points_within_pooled": 0.95, "nodes_90pct_within": 1.0, "duplicates": 0.0, "keyframes": 3.0,
            "pose_trans_cm_median": 0.1, "pose_rot_deg_median": 0.05}
    res = {"replay": figs, "in_process": dict(figs, accuracy_median_m=0.03), "comparison": {"gap_max": 0.3},
           "figures": {"latency_p50_s": 1.0, "latency_p99_s": 2.5, "latency_rest_p50_s": 1.0, "latency_rest_p99_s": 1.5,
                       "latency_first_s": [2.5], "first_keyframe_wait_s": 2.0, "frames_sent": 3, "frames_in_folder": 3},
           "in_process_run": {"counters": {"keyframes": 3.0}}}
    met = {r["figure"]: r["met"] for r in replay.summary_rows(res)}
    assert met["accuracy, median"] == "met" and met["completion @ 5 cm"] == "**miss**"
    assert met["node points within 10 cm (mean over nodes)"] == "met"
    assert met["capture -> graph latency p99"] == "**miss**"
    assert met["  the same, p50 / p99 without the first keyframe"] == "met"
    assert met["replay vs in-process, largest gap of the four above"] == "**miss**"


def test_the_first_keyframe_and_its_wait_for_a_second_view_are_reported_apart() -> None:
    captured = {0: 10_000_000_000, 1: 12_000_000_000, 2: 14_000_000_000}  # 0.5 Hz
    samples = [(10_000_000_000, 3100.0), (12_000_000_000, 1200.0), (10_000_000_000, 3300.0),
               (14_000_000_000, 1400.0)]
    out = replay.split_first_keyframe(samples, captured)
    assert out["latency_rest_s"] == [1.2, 1.4] and out["latency_first_s"] == [3.1, 3.3]
    assert out["first_keyframe_wait_s"] == 2.0 and out["latency_rest_p50_s"] == pytest.approx(1.3)
    assert out["latency_rest_p99_s"] == pytest.approx(1.398)
    empty = replay.split_first_keyframe([], {})
    assert empty["latency_rest_s"] == [] and math.isnan(empty["latency_rest_p99_s"])
    assert math.isnan(empty["first_keyframe_wait_s"])


def test_accuracy_is_binned_by_distance_from_the_cameras() -> None:
    pts = np.array([[0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [0.0, 4.0, 0.0]])
    rows = replay.accuracy_by_range(pts, np.array([0.01, 0.1, 0.3]), np.zeros((1, 3)))
    assert [(r["range_m"], r["points"]) for r in rows] == [("0-1.5", 1), ("1.5-3", 1), ("3-5", 1), ("5-inf", 0)]
    assert [r["accuracy_median_m"] for r in rows[:3]] == [0.01, 0.1, 0.3] and math.isnan(rows[3]["accuracy_median_m"])


def test_a_failed_process_is_named_by_its_last_lines() -> None:
    lines = ["[up] start mapper", "[mapper] argus mapper: invalid configuration in m.toml:",
             "[mapper]   geometry.backend: unknown reconstructor 'nope'", "[up] mapper exited with code 2"]
    assert replay._failure(lines, ["mapper"]) == ("argus mapper: invalid configuration in m.toml: / "
                                                  "geometry.backend: unknown reconstructor 'nope'")
    assert replay._failure(lines, ["camera"]) == "(no output)"


def test_the_map_is_also_scored_over_voxels_several_keyframes_saw() -> None:
    """A stray voxel one keyframe made (1 observation) counts in the published map's figures, not in the
    confirmed ones; with no counts there are no confirmed figures."""
    ref = plane(step_m=0.05)
    pts = np.concatenate([ref, [[0.5, 0.5, 1.0]]])
    counts = np.concatenate([np.full(len(ref), 3), [1]])
    result = replay.MapResult(pts, [], {}, {}, counts)
    figs, _, _ = replay.scored(result, ref, {})
    assert figs["map_points"] == len(ref) + 1 and figs["accuracy_mean_m"] > 0
    assert figs["confirmed_map_points"] == len(ref) and figs["confirmed_accuracy_mean_m"] == 0.0
    assert figs["confirmed_completion_5cm"] == 1.0
    no_counts, _, _ = replay.scored(replay.MapResult(pts, [], {}, {}), ref, {})
    assert "confirmed_map_points" not in no_counts
