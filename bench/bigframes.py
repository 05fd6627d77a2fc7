"""``argus bench bigframes``: the memory of an ``argus mapper`` fed streams of large frames, real and padded.

Each stream goes to a fresh router + mapper (real processes through :class:`deploy.up.Stack`; the mapper starts
no local worker, so it computes every keyframe itself: the most its own memory can take). This process plays
one moving camera: simulator renders (``--render`` pixels square, frames turning 15 degrees apart, so each is a
keyframe) upscaled to the stream's size and JPEG-encoded, and puts them one at a time, each once the mapper has
taken the one before (none is dropped: every frame costs what it costs). After the last it puts a small
sentinel frame: the mapper handles frames in order, so when the sentinel is counted the stream's last keyframe
is done. Reported per stream: the mapper's peak resident memory (``VmHWM`` of ``/proc/<pid>/status``) before
the first frame and at the end, what its Status counted (frames processed, refused per reason, keyframes,
``decoded_pixels_peak``), and the size each frame was worked at.

Streams (``--streams``, default all):

- ``ref-<r>``: the renders themselves, ``r`` x ``r`` (worked at full size): the reference;
- ``real-4000``, ``real-8000``: the renders upscaled to 4000x4000 / 8000x8000, baseline JPEG (4:2:0);
- ``real-8000-prog``: 8000x8000 progressive (libjpeg keeps the full image's DCT coefficients: 183 MiB);
- ``padded``: 4000x4000 and 8000x8000 claimed by a small real JPEG padded with comment segments up to the old
  byte-per-pixel floor (issue 37); ``padded-floor-off``: the same with ``min_jpeg_bytes_per_mpixel = 0``, so the
  mapper decodes them (the missing data grey), and a padded progressive 4:4:4 8000x8000 one (366 MiB of
  coefficients: over ``max_decode_bytes``);
- ``mixed``: the real and padded frames above interleaved, at the defaults;
- ``real-uhd``: renders of 1920x1080 upscaled to 3840x2160, worked at 1/2: at the largest working size
  (``max_working_pixels``), so the costliest frames per pixel processed.

Example (about 15 minutes on 2 cores)::

    argus bench bigframes --out bench_out/bigframes
    argus bench bigframes --quick --streams ref,real-8000,padded
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.report import write_report
from protocol.jpeg import jpeg_size
from protocol.messages import Intrinsics

COMMENT_SEGMENT_BYTES = 65533
"""The most payload one JPEG comment (COM) segment holds."""
OLD_FLOOR_BYTES_PER_MPIXEL = 1000.0
"""The mapper's default ``min_jpeg_bytes_per_mpixel``: a padded JPEG carries just over it."""


# --- frames -------------------------------------------------------------------------------------------
def encode_bgr(bgr: np.ndarray, quality: int = 90, progressive: bool = False, subsampling: str = "420") -> bytes:
    """A BGR image as a JPEG: baseline or progressive, chroma ``420`` or ``444``."""
    factor = {"420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420, "444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444}[subsampling]
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_PROGRESSIVE,
                                         int(progressive), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def textured_rgb(width: int, height: int, seed: int = 0, cell_px: int = 48) -> np.ndarray:
    """A real texture at ``width`` x ``height`` (smooth colour noise of ``cell_px`` cells with sharp discs on it),
    RGB uint8: compresses like a photograph, not like a flat image."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (max(2, height // cell_px), max(2, width // cell_px), 3), dtype=np.uint8)
    img = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(64):
        x, y = (int(v) for v in rng.integers(0, (width, height)))
        r = int(rng.integers(max(2, min(width, height) // 100), max(3, min(width, height) // 12)))
        cv2.circle(img, (x, y), r, tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
    return img


def textured_jpeg(width: int, height: int, seed: int = 0, quality: int = 90, progressive: bool = False) -> bytes:
    """:func:`textured_rgb` as a JPEG (4:2:0)."""
    return encode_bgr(textured_rgb(width, height, seed)[:, :, ::-1], quality, progressive)


def claim_size(jpeg: bytes, width: int, height: int) -> bytes:
    """``jpeg`` with its start-of-frame header rewritten to claim ``width`` x ``height`` (its data unchanged)."""
    b = bytearray(jpeg)
    i = 2
    while not (b[i] == 0xFF and 0xC0 <= b[i + 1] <= 0xCF and b[i + 1] not in (0xC4, 0xC8, 0xCC)):
        i += 2 + ((b[i + 2] << 8) | b[i + 3])
    b[i + 5 : i + 7] = height.to_bytes(2, "big")
    b[i + 7 : i + 9] = width.to_bytes(2, "big")
    return bytes(b)


def with_comments(jpeg: bytes, n_bytes: int) -> bytes:
    """``jpeg`` with ``n_bytes`` of comment segments (COM, ``FF FE``) inserted after its SOI marker."""
    segments = bytearray()
    while n_bytes > 0:
        n = min(n_bytes, COMMENT_SEGMENT_BYTES)
        segments += b"\xff\xfe" + (n + 2).to_bytes(2, "big") + b"A" * n
        n_bytes -= n
    return jpeg[:2] + bytes(segments) + jpeg[2:]


def padded_jpeg(width: int, height: int, progressive: bool = False, subsampling: str = "420",
                bytes_per_mpixel: float = OLD_FLOOR_BYTES_PER_MPIXEL * 1.1) -> bytes:
    """A 64x64 JPEG claiming ``width`` x ``height``, padded with comments to ``bytes_per_mpixel`` (issue 37: the
    plausibility floor on compressed bytes per pixel, passed by a file that holds almost no image)."""
    small = encode_bgr(textured_rgb(64, 64, 1)[:, :, ::-1], 90, progressive, subsampling)
    jpeg = claim_size(small, width, height)
    need = int(bytes_per_mpixel * width * height / 1e6)
    return with_comments(jpeg, max(0, need - len(jpeg)))


@dataclass
class Frame:
    """One frame of a stream: its JPEG, size, intrinsics and pose."""

    name: str
    jpeg: bytes
    intrinsics: Intrinsics
    T_world_cam: np.ndarray


def render(n: int, width: int, height: int, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray], Intrinsics]:
    """``n`` simulator renders (BGR, ``width`` x ``height``) of a camera turning 15 degrees a frame, their poses and
    intrinsics."""
    from bench.system import render_cameras
    from protocol.jpeg import decode_jpeg

    cam = render_cameras(1, n, width, height, "apartment", seed)[0]
    images = [decode_jpeg(j)[:, :, ::-1].copy() for j in cam.jpegs]  # the renders, decoded back once
    return images, cam.poses, cam.intrinsics


def upscaled(images: list[np.ndarray], poses: list[np.ndarray], intr: Intrinsics, scale: int, progressive: bool,
             label: str) -> list[Frame]:
    """The renders ``scale`` times larger (bicubic), JPEG-encoded one at a time (an 8000x8000 image is 192 MB)."""
    out = []
    w, h = intr.width * scale, intr.height * scale
    for i, (img, T) in enumerate(zip(images, poses, strict=True)):
        big = img if scale == 1 else cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
        out.append(Frame(f"{label}#{i}", encode_bgr(big, 90, progressive), intr.scaled(w, h), T))
        del big
    return out


def padded_frames(poses: list[np.ndarray], intr: Intrinsics, sizes: list[int], progressive_444: bool = False
                  ) -> list[Frame]:
    """Padded frames claiming each of ``sizes`` in turn (with ``progressive_444``: also an 8000x8000 progressive
    4:4:4 one, whose coefficients alone need 366 MiB)."""
    kinds: list[tuple[int, bool, str]] = [(s, False, "420") for s in sizes]
    if progressive_444:
        kinds.append((8000, True, "444"))
    out = []
    for i, T in enumerate(poses):
        s, prog, sub = kinds[i % len(kinds)]
        out.append(Frame(f"padded-{s}{'-prog444' if prog else ''}#{i}", padded_jpeg(s, s, prog, sub),
                         intr.scaled(s, s), T))
    return out


# --- one stream into one mapper ----------------------------------------------------------------------------
ACCOUNTED = ("frames_processed", "decode_errors", "frames_dropped", "frames_bad_intrinsics", "frames_outside_site",
             "frames_bad_pose", "header_errors", "frame_errors", "frames_over_decode_budget")
"""Mapper counters that together count every frame it has taken (processed, refused or dropped) once: an image
refused on arrival counts under its reason and as ``decode_errors``; only the latter is here."""
REPORTED = ("frames_in", "frames_processed", "keyframes", "decode_errors", "frames_too_large",
            "frames_implausible_jpeg", "frames_dropped", "decoded_pixels_peak", "keyframe_errors")


def _accounted(status: dict[str, float]) -> float:
    return sum(float(status.get(k, 0.0)) for k in ACCOUNTED)


def run_stream(frames: list[Frame], limits: dict[str, Any], frame_timeout_s: float = 300.0) -> dict[str, Any]:
    """Put ``frames`` into a fresh mapper one at a time, then the sentinel; its memory and counters."""
    from bench.system import GraphWatch, _launch, proc_mem_mb, stop_load
    from deploy.demo import free_endpoint
    from deploy.up import Stack
    from protocol.jpeg import encode_jpeg
    from protocol.keys import Keys
    from protocol.messages import FrameHeader, rows
    from protocol.session import ZenohSettings, open_session
    from protocol.transport import declare_frame_publisher, put_frame

    endpoint, site = free_endpoint(), "benchbig"
    keys = Keys(site)
    settings = {"workers": {"local": 0}, "status_period_s": 0.1, "limits": limits}
    lines: list[str] = []
    stack = Stack(_launch(endpoint, site, settings, 0, None), Path.cwd(), emit=lines.append)
    session = watch = None
    try:
        stack.start()
        if not stack.wait_healthy(180):
            raise RuntimeError("mapper did not come up:\n" + "\n".join(lines[-30:]))
        pid = next(c.pid for c in stack.children if c.spec.name == "mapper")
        assert pid is not None
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        watch = GraphWatch(session, keys)
        cam = declare_frame_publisher(session, keys.frame("robot", "bigcam"))
        sentinel_pub = declare_frame_publisher(session, keys.frame("fixed", "sentinel"))
        time.sleep(1.0)  # the mapper's subscriber matches ours
        before = proc_mem_mb(pid)
        t0 = time.monotonic()
        for seq, f in enumerate(frames):
            w, h = jpeg_size(f.jpeg)
            put_frame(cam, FrameHeader(source_id="bigcam", source_kind="robot", seq=seq, stamp_ns=time.time_ns(),
                                       width=w, height=h, intrinsics=f.intrinsics, T_world_cam=rows(f.T_world_cam)),
                      f.jpeg)
            _wait(watch, seq + 1, frame_timeout_s, f.name)
        tiny = encode_jpeg(np.full((48, 64, 3), 128, np.uint8))
        put_frame(sentinel_pub, FrameHeader(source_id="sentinel", source_kind="fixed", seq=0, stamp_ns=time.time_ns(),
                                            width=64, height=48), tiny)
        status = _wait(watch, len(frames) + 1, frame_timeout_s, "sentinel")
        after = proc_mem_mb(pid)
        return {"frames": len(frames), "seconds": time.monotonic() - t0,
                "mapper_peak_rss_mb_before": before["peak_rss_mb"], "mapper_peak_rss_mb": after["peak_rss_mb"],
                "mapper_rss_mb_end": after["rss_mb"], **{k: float(status.get(k, 0.0)) for k in REPORTED}}
    finally:
        stop_load([], watch, session, stack)


def _wait(watch: Any, n: int, timeout_s: float, what: str) -> dict[str, float]:
    """The mapper's Status once it has accounted for ``n`` frames (processed, refused or dropped)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = watch.take()[2]
        if _accounted(status) >= n:
            return status
        time.sleep(0.05)
    raise RuntimeError(f"the mapper did not take {what} in {timeout_s:.0f} s (status {watch.take()[2]})")


# --- the benchmark ------------------------------------------------------------------------------------------
STREAMS = ("ref", "real-4000", "real-8000", "real-8000-prog", "padded", "padded-floor-off", "mixed", "real-uhd")


def streams(names: list[str], n: int, size: int) -> dict[str, tuple[list[Frame], dict[str, Any]]]:
    """Each named stream's frames and mapper limits."""
    images, poses, intr = render(n, size, size)
    real = {s: upscaled(images, poses, intr, s // size, False, f"real-{s}") for s in (4000, 8000)
            if f"real-{s}" in names or "mixed" in names}
    out: dict[str, tuple[list[Frame], dict[str, Any]]] = {}
    if "ref" in names:
        out[f"ref-{size}"] = (upscaled(images, poses, intr, 1, False, f"ref-{size}"), {})
    for s, frames in real.items():
        if f"real-{s}" in names:
            out[f"real-{s}"] = (frames, {})
    if "real-8000-prog" in names:
        out["real-8000-prog"] = (upscaled(images, poses, intr, 8000 // size, True, "real-8000-prog"), {})
    if "padded" in names:
        out["padded"] = (padded_frames(poses, intr, [4000, 8000]), {})
    if "padded-floor-off" in names:
        out["padded-floor-off"] = (padded_frames(poses, intr, [4000, 8000], progressive_444=True),
                                   {"min_jpeg_bytes_per_mpixel": 0.0})
    if "mixed" in names:
        pads = padded_frames(poses, intr, [4000, 8000])
        mixed = [f for i in range(n) for f in (real[4000][i], pads[i], real[8000][i])]
        out["mixed"] = (mixed, {})
    if "real-uhd" in names:  # 3840x2160, worked at 1/2: the largest working size (1920x1080), the worst case
        hd_images, hd_poses, hd_intr = render(n, 1920, 1080)
        out["real-uhd"] = (upscaled(hd_images, hd_poses, hd_intr, 2, False, "real-uhd"), {})
    return out


def run(names: list[str], n: int, size: int, out: Path) -> dict[str, Any]:
    from mapper.intake import InputLimits

    lim = InputLimits()
    rows: list[dict[str, Any]] = []
    for name, (frames, limits) in streams(names, n, size).items():
        print(f"[bench bigframes] {name}: {len(frames)} frames, limits {limits or 'default'}", flush=True)
        r = run_stream(frames, limits)
        sizes = sorted({jpeg_size(f.jpeg) for f in frames})
        rows.append({"stream": name, "sizes": " ".join(f"{w}x{h}" for w, h in sizes),
                     "jpeg_mb_max": max(len(f.jpeg) for f in frames) / 1e6, **r})
        print(f"[bench bigframes] {name}: peak {r['mapper_peak_rss_mb']:.0f} MiB (before the first frame "
              f"{r['mapper_peak_rss_mb_before']:.0f}), processed {r['frames_processed']:.0f}, refused "
              f"{r['decode_errors']:.0f}, keyframes {r['keyframes']:.0f}", flush=True)
    results = {"limits": lim.model_dump(mode="json"), "render_px": size, "frames_per_stream": n, "streams": rows}
    write_report(out, "bigframes", results, rows,
                 title="argus mapper memory with large frames (python -m bench.bigframes)")
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="argus bench bigframes", description=__doc__.split("\n\n")[0],
                                epilog="example: argus bench bigframes --out bench_out/bigframes")
    p.add_argument("--frames", type=int, default=6, help="frames per stream (each a keyframe)")
    p.add_argument("--render", type=int, default=1000, help="side of the simulator renders, pixels (a divisor of "
                   "4000; real-uhd renders 1920x1080)")
    p.add_argument("--streams", default=",".join(STREAMS), help=f"comma-separated, of {', '.join(STREAMS)}")
    p.add_argument("--quick", action="store_true", help="3 frames per stream, renders of 500 pixels")
    p.add_argument("--out", default="bench_out/bigframes")
    a = p.parse_args(argv)
    names = [s.strip() for s in a.streams.split(",") if s.strip()]
    unknown = sorted(set(names) - set(STREAMS))
    if unknown:
        p.error(f"unknown streams {unknown}")
    n, size = (3, 500) if a.quick else (a.frames, a.render)
    if 4000 % size:
        p.error("--render must divide 4000")
    run(names, n, size, Path(a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
