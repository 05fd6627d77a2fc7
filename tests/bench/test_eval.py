"""``argus eval``: the experiments run end to end and write well-formed, non-trivial outputs."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from bench.eval import EvalConfig, ExternalConfig, FramesConfig, StaticConfig, main, quick_config, run

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


def _check_outputs(out: Path, names: list[str]) -> dict[str, dict]:
    results = {}
    for name in names:
        res = json.loads((out / f"{name}.json").read_text())
        md = (out / f"{name}.md").read_text()
        assert md.startswith("## ") and "|---|" in md, md
        w, h = _png_size(out / f"{name}.png")
        assert w > 200 and h > 100
        results[name] = res
    summary = (out / "summary.md").read_text()
    assert all(f"{n}" in summary.lower() for n in names)
    return results


def test_static_and_external_tiny(tmp_path: Path) -> None:
    """A tiny in-process run with ORACLE geometry (fast): scores are real, not trivially zero."""
    cfg = EvalConfig(
        out=tmp_path, experiments=["static", "external"],
        static=StaticConfig(seeds=[0], geometries=["oracle"], frames=FramesConfig(n_frames=4, width=160, height=120)),
        external=ExternalConfig(families=["furnished_room"], seeds=[0], cameras=[1, 2], geometries=["oracle"],
                                width=160, height=120),
    )
    run(cfg, log=lambda m: None)
    res = _check_outputs(tmp_path, ["static", "external"])
    s = res["static"]["summary"][0]
    assert s["geometry"] == "oracle" and 0 < s["precision"] <= 1 and 0 < s["recall"] <= 1 and s["n_pred"] > 0
    ext = res["external"]["summary"]
    assert [e["cameras"] for e in ext] == [1, 2]
    assert all(0 < e["recall"] <= 1 for e in ext)
    # More cameras never see fewer of the scene's objects here (the second camera adds a corner).
    assert ext[1]["n_pred"] >= ext[0]["n_pred"]
    assert "ORACLE" in (tmp_path / "external.md").read_text()


def test_static_mapper_overrides_reach_the_mapper(tmp_path: Path) -> None:
    """``[static.mapper]`` is written over the mapper's configuration: masks no detection reaches leave no node."""
    from pydantic import ValidationError

    frames = FramesConfig(n_frames=3, width=160, height=120)
    big = {"fusion": {"min_mask_pixels": 10**6}}
    cfg = EvalConfig(out=tmp_path, experiments=["static"],
                     static=StaticConfig(seeds=[0], geometries=["oracle"], frames=frames, mapper=big))
    run(cfg, log=lambda m: None)
    (row,) = json.loads((tmp_path / "static.json").read_text())["per_scene"]
    assert row["n_pred"] == 0 and row["recall"] == 0
    bad = EvalConfig(out=tmp_path, experiments=["static"],
                     static=StaticConfig(seeds=[0], geometries=["oracle"], frames=frames,
                                         mapper={"fusion": {"no_such_field": 1}}))
    with pytest.raises(ValidationError, match="no_such_field"):
        run(bad, log=lambda m: None)


def test_static_probe_geometry_is_named_as_an_oracle(tmp_path: Path) -> None:
    """``probe:<pixels>`` runs the ORACLE diagnostic backend with that option, and its table row says ORACLE."""
    from pydantic import ValidationError

    from bench.explore import core_config

    geo = core_config("probe:objects", "sim").geometry
    assert geo.backend == "probe" and geo.options.truth_at == "objects"
    with pytest.raises(ValueError, match="only probe"):
        core_config("mvs:objects", "sim")
    with pytest.raises(ValidationError, match="truth_at"):
        core_config("probe:everywhere", "sim")
    frames = FramesConfig(n_frames=3, width=160, height=120)
    cfg = EvalConfig(out=tmp_path, experiments=["static"],
                     static=StaticConfig(seeds=[0], geometries=["probe:confident"], frames=frames))
    run(cfg, log=lambda m: None)
    (entry,) = json.loads((tmp_path / "static.json").read_text())["summary"]
    assert entry["experiment"].startswith("ORACLE probe") and entry["geometry"] == "probe:confident"


def test_cli_rejects_unknown_experiment(tmp_path: Path) -> None:
    assert main(["nonsense", "--out", str(tmp_path)]) == 2


def test_cli_writes_where_the_config_says_unless_told(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[EvalConfig] = []
    monkeypatch.setattr("bench.eval.run", lambda cfg: seen.append(cfg))
    conf = tmp_path / "static.toml"
    conf.write_text(f'out = "{tmp_path / "from_config"}"\nexperiments = ["static"]\n')
    assert main(["--config", str(conf)]) == 0
    assert main(["--config", str(conf), "--out", str(tmp_path / "from_cli")]) == 0
    assert [c.out for c in seen] == [tmp_path / "from_config", tmp_path / "from_cli"]
    assert seen[0].experiments == ["static"]


def test_quick_config_is_small() -> None:
    cfg = quick_config(Path("x"))
    assert cfg.experiments == ["static", "external", "active"]
    assert len(cfg.static.seeds) == 1 and cfg.active.starts == 1 and cfg.active.steps <= 5


@pytest.mark.slow
def test_eval_quick_end_to_end(tmp_path: Path) -> None:
    """``argus eval --quick``: all three experiments, mvs included, under five minutes."""
    import time

    t0 = time.monotonic()
    assert main(["--quick", "--out", str(tmp_path)]) == 0
    assert time.monotonic() - t0 < 300
    res = _check_outputs(tmp_path, ["static", "external", "active"])
    geos = {s["geometry"]: s for s in res["static"]["summary"]}
    assert set(geos) == {"oracle", "mvs"} and geos["oracle"]["recall"] > 0 and geos["mvs"]["n_pred"] > 0
    curves = res["active"]["curves"]
    assert {(c["geometry"], c["strategy"], c["external"]) for c in curves} == {
        ("mvs", "see", False), ("mvs", "see", True), ("mvs", "asp", False), ("mvs", "asp", True)}
    assert all(c["nodes_mean"][-1] > 0 for c in curves)
    assert all(e["recall"] > 0 for e in res["external"]["summary"] if e["geometry"] == "oracle")
    assert {e["geometry"] for e in res["external"]["summary"]} == {"oracle", "mvs"}


def test_active_runs_rgb_only_first_then_the_true_geometry_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    import bench.explore
    from bench.eval import ActiveConfig, active_markdown, run_active, steps_to

    calls: list[dict] = []

    def fake_episode(**kw):  # noqa: ANN003, ANN202 - run_episode's keyword interface
        calls.append(kw)
        gain = 0.3 if kw["geometry"] == "mvs" else 0.45
        return {"steps": [{"step": i, "n_nodes": 10 * i, "recall": min(1.0, gain * i), "distance_m": 2.0 * i}
                          for i in range(kw["steps"] + 1)]}

    monkeypatch.setattr(bench.explore, "run_episode", fake_episode)
    res = run_active(ActiveConfig(steps=3, starts=2, strategies=["asp"], external=[False]), 1, lambda m: None)
    assert [(c["geometry"], c["reference"]) for c in res["curves"]] == [("mvs", False), ("oracle", True)]
    assert all(kw["goal_capture_m"] == 0.3 for kw in calls)  # the robot's capture in every run alike
    assert [kw.get("move_frames") for kw in calls] == [2, 2, None, None]
    mvs, ref = res["curves"]
    assert mvs["steps_to"] == {"50%": 2, "80%": 3} and ref["steps_to"] == {"50%": 2, "80%": 2}
    assert mvs["distance_mean"] == [0.0, 2.0, 4.0, 6.0]
    md = active_markdown(res)
    assert "ASP (oracle geometry)" in md and "Steps to 80 %" in md
    assert steps_to([0.1, 0.4], 0.5) is None
