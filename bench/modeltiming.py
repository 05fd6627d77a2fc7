"""Seconds per batch of N views for a reconstructor (``argus bench geometry --batch-views 8 32``).

Speed does not depend on the weights, so a random-weight model serves: ``--random-weights da3-base`` builds
Depth Anything 3 of that size with random weights (no checkpoint needed); MapAnything needs ``--opt
checkpoint=DIR`` (its full-size configuration lives in its repository). The views are the real TUM frames
(repeated to N) with their recorded poses and intrinsics, at their native 640x480 (each model resizes to its
own working resolution). A CUDA device that is not present gives ``measured: false`` with the reason,
never numbers from another device.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from mapper.geometry.contract import View


def tum_views(n: int) -> list[View]:
    """``n`` views cycling through the TUM fr1/xyz frames (ValueError when the data is absent)."""
    from dataclasses import replace

    from bench.video import available, load_sequence

    if not available("tum-fr1-xyz"):
        raise ValueError("timing needs ../shared/data/tum-fr1-xyz")
    frames, _ = load_sequence("tum-fr1-xyz")
    return [replace(frames[i % len(frames)].view, seq=i) for i in range(n)]


def device_of(opts: dict[str, Any]) -> tuple[str, str | None]:
    """(device, reason it cannot be measured or None)."""
    device = str(opts.get("device", "cpu"))
    try:
        import torch
    except ImportError:
        return device, "torch is not installed"
    if device.startswith("cuda") and not torch.cuda.is_available():
        return device, "not measured: no GPU on this machine (torch.cuda.is_available() is False)"
    return device, None


def gpu_name(device: str) -> str | None:
    if not device.startswith("cuda"):
        return None
    import torch

    return str(torch.cuda.get_device_name(torch.device(device)))


def time_batches(rec: Any, sizes: Sequence[int], repeats: int = 3) -> list[dict[str, Any]]:
    """Median seconds of ``rec.reconstruct`` for each batch size, after one warm-up call per size."""
    out = []
    for n in sizes:
        views = tum_views(n)
        rec.reconstruct(views)  # warm-up: allocations, kernel selection
        secs = []
        for _ in range(repeats):
            _sync()
            t = time.perf_counter()
            rec.reconstruct(views)
            _sync()
            secs.append(time.perf_counter() - t)
        out.append({"views": n, "seconds_per_batch": statistics.median(secs),
                    "seconds_per_view": statistics.median(secs) / n, "repeats": repeats})
    return out


def _sync() -> None:
    try:
        import torch
    except ImportError:
        return
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def batch_timing(backend: str, opts: dict[str, Any], sizes: Sequence[int], random_weights: str | None = None,
                 repeats: int = 3) -> dict[str, Any]:
    """The timing report section (see module docstring)."""
    from mapper.geometry.registry import make_reconstructor

    device, why_not = device_of(opts)
    report: dict[str, Any] = {"backend": backend, "device": device, "sizes": list(sizes),
                              "random_weights": random_weights, "measured": why_not is None}
    if why_not is not None:
        report["reason"] = why_not
        return report
    report["gpu"] = gpu_name(device)
    with tempfile.TemporaryDirectory() as tmp:
        if random_weights is not None:
            if backend != "da3":
                raise ValueError("--random-weights is only for the da3 backend (MapAnything: --opt checkpoint=DIR)")
            from depth_anything_3.api import DepthAnything3

            DepthAnything3(model_name=random_weights).save_pretrained(tmp)
            opts = {**opts, "checkpoint": tmp}
        rec = make_reconstructor(backend, **opts)
        report["batches"] = time_batches(rec, sizes, repeats)
    return report


def perception_timing(segmenter: str, embedder: str, seg_opts: dict[str, Any], emb_opts: dict[str, Any],
                      frames: int = 5) -> dict[str, Any]:
    """Median seconds per 640x480 real frame of ``segmenter`` + ``embedder`` (e.g. sam + clip with
    ``random_init=true``: speed does not depend on the weights), after one warm-up frame."""
    from mapper.perception.registry import make_embedder, make_segmenter

    device, why_not = device_of({"device": seg_opts.get("device", emb_opts.get("device", "cpu"))})
    report: dict[str, Any] = {"segmenter": segmenter, "embedder": embedder, "device": device,
                              "measured": why_not is None}
    if why_not is not None:
        report["reason"] = why_not
        return report
    report["gpu"] = gpu_name(device)
    seg, emb = make_segmenter(segmenter, **seg_opts), make_embedder(embedder, **emb_opts)
    views = tum_views(frames + 1)
    t_seg, t_emb, n_masks = [], [], []
    for i, v in enumerate(views):
        _sync()
        t0 = time.perf_counter()
        masks = seg.segment(v)
        _sync()
        t1 = time.perf_counter()
        emb.embed(v, masks)
        _sync()
        if i:  # the first frame warms up
            t_seg.append(t1 - t0)
            t_emb.append(time.perf_counter() - t1)
            n_masks.append(len(masks))
    report.update(frames=frames, segment_s=statistics.median(t_seg), embed_s=statistics.median(t_emb),
                  total_s=statistics.median([a + b for a, b in zip(t_seg, t_emb, strict=True)]),
                  masks_per_frame=statistics.mean(n_masks))
    return report


def _kv(items: Sequence[str]) -> dict[str, Any]:
    import json

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"expected KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``argus bench perception``: seconds per frame of a segmenter + embedder on real frames."""
    import argparse
    import json
    from pathlib import Path

    p = argparse.ArgumentParser(
        prog="argus bench perception", description="Seconds per real 640x480 frame of a segmenter + embedder.",
        epilog="example (GPU, random weights): argus bench perception --segmenter sam --embedder clip "
        "--seg-opt random_init=true --emb-opt random_init=true --seg-opt device=cuda --emb-opt device=cuda",
    )
    p.add_argument("--segmenter", default="detector", help="segmenter backend")
    p.add_argument("--embedder", default="detector", help="embedder backend")
    p.add_argument("--seg-opt", action="append", default=[], metavar="KEY=VALUE", help="segmenter option (JSON)")
    p.add_argument("--emb-opt", action="append", default=[], metavar="KEY=VALUE", help="embedder option (JSON)")
    p.add_argument("--frames", type=int, default=5, help="timed frames (after one warm-up)")
    p.add_argument("--quick", action="store_true", help="accepted for `argus bench all`")
    p.add_argument("--out", type=Path, default=None, help="directory for perception.json")
    a = p.parse_args(list(argv) if argv is not None else None)
    rep = perception_timing(a.segmenter, a.embedder, _kv(a.seg_opt), _kv(a.emb_opt), a.frames)
    print(json.dumps(rep, indent=1))
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "perception.json").write_text(json.dumps(rep, indent=1))
    return 0
