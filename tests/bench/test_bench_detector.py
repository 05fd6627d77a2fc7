"""``argus bench detector`` on the real TUM desk frames: labelled nodes land on their objects."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.video import available, load_sequence

pytestmark = pytest.mark.skipif(not available("tum-fr1-xyz"), reason="real frames ../shared/data/tum-fr1-xyz absent")


def test_detector_nodes_on_the_desk(tmp_path: Path) -> None:
    from bench.detector import main, project

    assert main(["--out", str(tmp_path), "--sequences", "tum-fr1-xyz"]) == 0
    report = json.loads((tmp_path / "detector.json").read_text())
    seq = report["sequences"][0]
    labels = {n["label"] for n in seq["nodes"]}
    assert {"Computer monitor", "Desk", "Chair"} <= labels, labels
    assert len(list(tmp_path.glob("tum-fr1-xyz-frame-*.png"))) == 10
    assert (tmp_path / "tum-fr1-xyz-nodes-first.png").is_file()
    frames, _ = load_sequence("tum-fr1-xyz")
    by_seq = {f.view.seq: f for f in frames}
    # every node seen at least twice projects inside a same-label box in most frames that have one
    for n in seq["nodes"]:
        if n["observations"] < 2:
            continue
        hits = total = 0
        for pf in seq["per_frame"]:
            boxes = [b["box"] for b in pf["boxes"] if b["label"] == n["label"]]
            if not boxes:
                continue
            uv = project(np.array(n["centroid"]), by_seq[pf["seq"]])
            total += 1
            hits += uv is not None and any(b[0] <= uv[0] <= b[2] and b[1] <= uv[1] <= b[3] for b in boxes)
        assert total and hits / total >= 0.8, (n, hits, total)


@pytest.mark.slow  # ~18 s: the whole core on real frames; the detector's own accuracy is checked above
def test_mapper_with_rgb_only_geometry_and_the_detector_labels_the_desk() -> None:
    """The whole mapper core (mvs geometry from the images and recorded poses, detector perception) on the
    10 TUM frames: labelled nodes for the desk and the monitor, near where the recorded depth puts them."""
    from mapper.config import MapperCoreConfig
    from mapper.core import MapperCore

    cfg = MapperCoreConfig.model_validate(
        {"geometry": {"backend": "mvs"}, "perception": {"segmenter": "detector", "embedder": "detector"}}
    )
    core = MapperCore(cfg)
    frames, _ = load_sequence("tum-fr1-xyz")
    for f in frames:
        core.ingest(f.view, force_keyframe=True)
    nodes = {n.label: np.array(n.box.center) for n in core.nodes()}
    # recorded-depth positions from `argus bench detector` (median of the fused points)
    assert np.linalg.norm(nodes["Desk"] - [0.554, 0.533, 0.754]) < 0.3
    assert np.linalg.norm(nodes["Computer monitor"] - [0.494, 0.915, 1.043]) < 0.35


def test_truth_summary_counts_boxes_on_true_objects_and_the_models_best_classes() -> None:
    from bench.detector import truth_summary

    per_frame: list[dict[str, Any]] = [
        {"boxes": [{"label": "Box", "true_object": 7}, {"label": "Desk", "true_object": 0}],
         "true_objects": {7: {"box": [0, 0, 5, 5], "labels": ["Box"], "evidence": {"Box": 0.5, "Book": 0.2}},
                          9: {"box": [5, 5, 9, 9], "labels": [], "evidence": {"Mug": 0.3}}}},
        {"boxes": [],
         "true_objects": {7: {"box": [0, 0, 5, 5], "labels": [], "evidence": {"Book": 0.4, "Box": 0.3}},
                          9: {"box": [5, 5, 9, 9], "labels": [], "evidence": {"Mug": 0.1, "Cat": 0.2}}}},
    ]
    lines = truth_summary(per_frame)
    # median over frames, 0 where a class is not among a frame's best: Box (0.5, 0.3) 0.4, Book (0.2, 0.4) 0.3
    assert "| 7 | 1/2 | Box | Box 0.40, Book 0.30 |" in lines
    assert "| 9 | 0/2 | - | Mug 0.20, Cat 0.10 |" in lines
    assert "boxes on no true object: 1 (Desk)" in lines
    assert truth_summary([{"boxes": []}]) == []


def test_bad_detector_options_are_one_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    from bench.detector import main

    for bad in (["--option", "bogus=1"], ["--option", "tile_grid=9"], ["--option", "no-equals-sign"]):
        with pytest.raises(SystemExit) as e:
            main([*bad, "--sequences", "tum-fr1-xyz"])
        assert e.value.code == 2
    err = capsys.readouterr().err
    assert "bogus" in err and "tile_grid" in err and "KEY=VALUE" in err and "Traceback" not in err
