"""`argus bench geometry` pieces that need no scene: depth scoring and the report."""

from __future__ import annotations

import numpy as np
import pytest

from bench.geometry import check_bars, main, markdown, score_depth


def test_score_depth_exact() -> None:
    gt = np.full((2, 4), 2.0, np.float32)
    pred = np.array([[2.2, 1.8, 2.0, 4.0], [2.0, 2.0, 2.0, 2.0]], np.float32)
    conf = np.array([[1, 1, 1, 1], [1, 1, 0, 0]], np.float32)
    valid = np.ones((2, 4), bool)
    valid[1, 1] = False
    s = score_depth(pred, conf, gt, valid)
    # confident & valid: 2.2, 1.8, 2.0, 4.0, 2.0 -> abs rel 0.1, 0.1, 0, 1.0, 0 -> median 0.1
    assert s.absrel == pytest.approx(0.1)
    assert s.delta125 == pytest.approx(4 / 5)
    assert s.confident == pytest.approx(5 / 7)
    assert s.n_gt == 7
    empty = score_depth(pred, np.zeros_like(conf), gt, valid)
    assert empty.confident == 0.0 and np.isnan(empty.absrel)


def test_bars_and_markdown_report_misses() -> None:
    frames = [{"seconds": 3.0, "cpu_seconds": 1.0}]
    depth = {"scenario": "x", "n_keyframes": 1, "median_absrel": 0.2, "median_delta125": 0.9, "median_confident": 0.8,
             "mean_confident": 0.8, "median_s_per_keyframe": 3.0, "p90_s_per_keyframe": 3.0,
             "median_cpu_s_per_keyframe": 1.0}
    report = {"backend": "mvs", "machine": "m", "cpus": 2, "load_avg": "0", "sim": None,
              "real": {"depth": [depth], "depth_frames": {"x": frames}}}
    report["bars"] = check_bars(report)
    met = {b["bar"]: b["met"] for b in report["bars"]}
    assert met["real frames: median AbsRel"] is False and met["real frames: confident fraction"] is True
    text = markdown(report)
    assert "| real frames: median AbsRel | <= 0.1 | 0.200 | False |" in text


def test_help_exits_cleanly(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    assert "argus bench geometry" in capsys.readouterr().out
