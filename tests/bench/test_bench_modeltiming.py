"""``argus bench geometry --batch-views``: timing plumbing that never reports numbers from the wrong device."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.geometry import main
from bench.modeltiming import device_of


def test_cuda_without_gpu_is_not_measured(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    assert device_of({"device": "cuda"})[1] is not None and device_of({})[1] is None
    assert main(["--backend", "da3", "--batch-views", "8", "32", "--opt", "device=cuda", "--out", str(tmp_path)]) == 0
    rep = json.loads((tmp_path / "geometry.json").read_text())["batch_timing"]
    assert rep["measured"] is False and rep["sizes"] == [8, 32] and "no GPU" in rep["reason"]


def test_perception_timing_detector_and_cuda_request(tmp_path: Path) -> None:
    from bench.modeltiming import main as perception_main
    from bench.video import available

    if not available("tum-fr1-xyz"):
        pytest.skip("real frames ../shared/data/tum-fr1-xyz absent")
    assert perception_main(["--frames", "2", "--out", str(tmp_path)]) == 0
    rep = json.loads((tmp_path / "perception.json").read_text())
    assert rep["measured"] and rep["frames"] == 2 and 0 < rep["segment_s"] < 10 and rep["masks_per_frame"] >= 1
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        assert perception_main(["--segmenter", "sam", "--embedder", "clip", "--seg-opt", "device=cuda",
                                "--out", str(tmp_path)]) == 0
        rep = json.loads((tmp_path / "perception.json").read_text())
        assert rep["measured"] is False and "no GPU" in rep["reason"]
