"""`argus bench geometry` pieces that need no scene: depth scoring and the report."""

from __future__ import annotations

import numpy as np
import pytest

from bench.geometry import check_bars, main, markdown, score_depth, worst_rows


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


def _row(name: str, declared: str, absrel: float, scale: float) -> dict:
    from bench.geomscore import ScenarioResult

    res = ScenarioResult(f"{name}, {declared}")
    res.seconds.append(0.3)
    res.frames.append({"n_gt": 100, "absrel": absrel, "delta125": 0.95, "confident": 0.6, "scale": scale,
                       "seconds": 0.3, "cpu_seconds": 0.3, "t_poses_s": 0.1, "t_dense_s": 0.2, "rot_deg_before": 0.0,
                       "rot_deg_after": 0.0, "trans_cm_before": 0.0, "trans_cm_after": 0.0})
    return dict(res.summary(), sequence=name, declared=declared)


def test_the_worst_sequence_decides_and_misses_are_reported() -> None:
    rows = [_row("a", "undeclared", 0.05, 0.99), _row("b", "undeclared", 0.09, 1.05), _row("a", "declared", 0.04, 1.0),
            _row("b", "declared", 0.05, 1.0), dict(_row("sim", "x", 0.5, 1.0), declared=None)]
    frames = {r["scenario"]: [{"seconds": 0.3}] for r in rows}
    report = {"backend": "mvs", "machine": "m", "cpus": 2, "load_avg": "0", "sim": None,
              "video": {"depth": rows, "depth_frames": frames}}
    worst = {w["declared"]: w for w in worst_rows(rows)}
    assert worst["undeclared"]["absrel"] == 0.09 and worst["undeclared"]["absrel_at"] == "b"
    assert worst["undeclared"]["scale"] == 1.05 and worst["declared"]["absrel"] == 0.05
    report["bars"] = check_bars(report)
    met = {b["bar"]: b["met"] for b in report["bars"]}
    assert met["worst recorded sequence, undeclared: AbsRel (b)"] is False
    assert met["worst recorded sequence, declared: AbsRel (b)"] is True
    assert met["worst recorded sequence, undeclared: scale (b)"] is False
    text = markdown(report)
    assert "| worst recorded sequence, undeclared: AbsRel (b) | <= 0.08 | 0.090 | False |" in text
    assert "| undeclared | 2 | 0.090 (b) |" in text


def test_a_broken_sequence_folder_is_one_line_naming_the_file(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.support.recorded import write_sequence

    folder = write_sequence(tmp_path / "seq", n=2)
    with pytest.raises(SystemExit) as e:
        main(["--only-video", "--no-sim", "--sequence", str(folder)])
    assert e.value.code == 2
    assert f"{folder / 'meta.json'}: missing" in capsys.readouterr().err


def test_help_exits_cleanly(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    assert "argus bench geometry" in capsys.readouterr().out


def test_the_report_opens_with_cpu_seconds_per_keyframe() -> None:
    from bench.geometry import cpu_headline

    row = {"median_cpu_s_per_keyframe": 0.5}
    report = {"sim": {"depth": [row, {"median_cpu_s_per_keyframe": 1.0}]}, "real": None,
              "video": {"depth": [{"median_cpu_s_per_keyframe": 0.25}, {"median_cpu_s_per_keyframe": float("nan")}]}}
    line = cpu_headline(report)
    assert line is not None and line.startswith("**0.50 CPU-seconds per keyframe** (median over 3 scenarios, 0.25-1.00")
    assert "one core carries 2.0 cameras at one keyframe per second each" in line
    assert cpu_headline({"sim": None, "real": None, "video": None}) is None
