"""``argus demo``: launch preparation, labelling of ORACLE inputs, the recording, and (slow) a real run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from deploy.demo import DEFAULT_LAUNCH, DemoConfig, Recorder, format_table, perception_label, prepare_launch
from protocol.messages import GraphEdge, GraphNode, GraphSnapshot, OrientedBox, PointMap
from tests.support.procs import Proc

LAUNCH_DIR = DEFAULT_LAUNCH.parent


def test_prepare_launch_applies_steps_and_a_free_port() -> None:
    launch = prepare_launch(DemoConfig(steps=7))
    robots = [p for p in launch.process if p.command == "robot-agent"]
    assert robots and all(p.settings["budget"]["max_steps"] == 7 for p in robots)
    assert launch.endpoint.startswith("tcp/127.0.0.1:") and launch.endpoint != "tcp/127.0.0.1:7447"
    assert launch.world is not None
    kept = prepare_launch(DemoConfig(free_port=False))
    assert kept.endpoint == "tcp/127.0.0.1:7447"


def test_demo_port_puts_the_router_on_that_port(monkeypatch: pytest.MonkeyPatch) -> None:
    assert prepare_launch(DemoConfig(port=7599)).endpoint == "tcp/127.0.0.1:7599"
    import deploy.demo as demo

    seen: list[DemoConfig] = []
    monkeypatch.setattr(demo, "run", lambda config: seen.append(config) or 0)
    assert demo.main(["--port", "7601", "--steps", "3"]) == 0
    assert seen[0].port == 7601 and prepare_launch(seen[0]).endpoint == "tcp/127.0.0.1:7601"
    assert demo.main(["--port", "0"]) == 2  # out of range: one line, usage status
    with pytest.raises(SystemExit):
        demo.main(["--port", "7601", "--keep-port"])  # one or the other


def _point_map(n: int, seed: int = 0) -> PointMap:
    rng = np.random.default_rng(seed)
    pts = (np.floor(rng.uniform(0, 8, size=(n, 3)) / 0.05) * 0.05 + 0.025).astype(np.float32)
    return PointMap(version=1, stamp_ns=1, voxel_m=0.05, points=pts,
                    colors=rng.integers(0, 255, size=(n, 3), dtype=np.uint8))


def test_recorder_logs_the_point_map_as_deltas(tmp_path: Path) -> None:
    """The demo sees the whole point map at every scoring period; its recording grows with the map, not with
    the map times the periods (it was 90 MB for one demo)."""
    whole = _point_map(40_000)

    def recorded(periods: int) -> int:
        path = tmp_path / f"p{periods}.rrd"
        rec = Recorder(path)
        for i in range(periods):
            n = 20_000 + i * 1_000  # a growing map: the first rows of the same points
            rec.log_world(i, float(i), {}, {}, whole.model_copy(update={
                "points": whole.points[:n], "colors": None if whole.colors is None else whole.colors[:n]}), {})
        rec.close()
        return path.stat().st_size

    once, twenty = recorded(1), recorded(20)
    assert twenty < 2.5 * once, (once, twenty)  # 20 whole maps would be > 20x


def test_recorded_boxes_show_their_labels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = Recorder(tmp_path / "l.rrd")
    logged: dict[str, object] = {}
    monkeypatch.setattr(rec.rec, "log", lambda path, arch, **kw: logged.__setitem__(path, arch))
    rec.log_graph(1, 0.5, _snap())
    assert logged["world/objects"].show_labels is not None  # type: ignore[attr-defined]


def test_oracle_inputs_are_labelled() -> None:
    default = perception_label(prepare_launch(DemoConfig()))
    assert default.startswith("RGB-only geometry") and "ORACLE 2D perception" in default
    oracle = perception_label(prepare_launch(DemoConfig(launch=LAUNCH_DIR / "demo-oracle.toml")))
    assert oracle.startswith("ORACLE geometry")
    rgb = perception_label(prepare_launch(DemoConfig(launch=LAUNCH_DIR / "demo-rgb-only.toml")))
    assert "ORACLE" not in rgb


def _snap() -> GraphSnapshot:
    box = OrientedBox(center=(1.0, 2.0, 0.5), extent=(0.5, 0.5, 1.0), yaw_rad=0.3)
    nodes = [GraphNode(node_id=f"n{i}", label=lab, label_confidence=0.9, centroid=(1.0 + i, 2.0, 0.5), box=box,
                       point_count=10, observation_count=1, first_seen_ns=1, last_seen_ns=1)
             for i, lab in enumerate(["chair", "table"])]
    return GraphSnapshot(version=3, stamp_ns=1, nodes=nodes,
                         edges=[GraphEdge(subject_id="n0", predicate="next_to", object_id="n1")])


def test_recorder_writes_a_rerun_file(tmp_path: Path) -> None:
    path = tmp_path / "x.rrd"
    rec = Recorder(path)
    rec.log_graph(1, 0.5, _snap())
    rec.log_metrics(1, 0.5, 2, 0.5, 1.0)
    rec.close()
    data = path.read_bytes()
    assert data[:4] == b"RRF2" and len(data) > 1000


def test_format_table() -> None:
    t = format_table([("nodes", "12"), ("recall", "0.500")])
    assert "| nodes  | 12 " in t and "| recall | 0.500 " in t and t.count("+") == 6


@pytest.mark.slow
def test_demo_runs_the_stack_and_scores_it(tmp_path: Path, procs: list[Proc]) -> None:
    """A short real run (ORACLE launch file, 2 steps): every process up, a scored graph, a recording."""
    p = Proc(["demo", "--launch", str(LAUNCH_DIR / "demo-oracle.toml"), "--steps", "2", "--rrd",
              str(tmp_path / "d.rrd"), "--json", str(tmp_path / "d.json"), "--log-dir", str(tmp_path / "logs")])
    procs.append(p)
    assert p.wait(300) == 0, p.output
    res = json.loads((tmp_path / "d.json").read_text())
    assert res["steps"] >= 2 and res["nodes"] > 0 and 0 < res["recall"] <= 1 and res["precision"] > 0
    rooms = res["rooms"]  # objects found per room of the apartment: they add up to the recall
    assert len(rooms) >= 3 and sum(r["objects"] for r in rooms.values()) == res["n_true"]
    assert sum(r["found"] for r in rooms.values()) == round(res["recall"] * res["n_true"])
    assert "| objects found in " in p.output
    assert (tmp_path / "d.rrd").stat().st_size > 10_000
    assert "argus demo: all processes stopped" in p.output and "| precision" in p.output
    assert {f.name for f in (tmp_path / "logs").iterdir()} >= {"mapper.log", "planner.log", "robot0.log"}
