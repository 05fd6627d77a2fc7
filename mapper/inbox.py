"""Frames from their arrival to a decoded :class:`View`: the mapper's intake (no session, no graph).

Each frame sample is checked as it arrives, before it takes a ring slot (``config.limits``,
:mod:`mapper.intake`): compressed size, pixel count, the JPEG's own size against its header, compressed
bytes per pixel, intrinsics and the camera position against the site's box; a refused frame is counted
under its reason and never decoded. Its pose is checked too (:func:`protocol.poses.check_pose`): a
nearly rigid one is projected onto SO(3) (counter ``poses_projected``); any other is dropped with its
frame (``frames_bad_pose``). A header that does not decode (a non-finite pose or intrinsics, a wrong
shape) counts as ``header_errors``. Every kind of bad input is logged as a WARNING, rate-limited.

Memory is bounded: compressed frames wait in a newest-frames ring per source (``ring_depth``, under
``limits.max_buffered_frame_bytes``), plus the same bound for frames waiting for their ORACLE sample, and
frames are decoded one at a time, just before processing, under ``limits.decode_budget_pixels``. Each is decoded
at its working size (:func:`mapper.intake.working_reduction`: 1/1, 1/2, 1/4 or 1/8 of its size, at most
``limits.max_working_pixels``; libjpeg's DCT scaling, in at most ``limits.max_decode_bytes``), its intrinsics
scaled alike (:meth:`protocol.messages.Intrinsics.reduced`) and its ORACLE images brought to the same pixel grid
(:func:`reduce_nearest`).

A header's ``pose_covariance`` becomes the view's prior accuracy (:class:`PriorAccuracy`); a covariance that
is not one (a negative or non-finite variance) is counted (``frames_bad_covariance``) and the frame goes on
as one that declared nothing: the reconstructor then judges its prior's accuracy from the images.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from mapper.config import MapperConfig
from mapper.geometry.contract import OracleData, View
from mapper.intake import IMAGE_REASONS, frame_problem, working_reduction
from protocol.codec import DecodeError
from protocol.jpeg import JpegError, decode_jpeg, jpeg_info, reduced_size
from protocol.keys import Keys
from protocol.messages import OracleFrame
from protocol.oracle import PNG_DECODE_BYTES_PER_PIXEL, decode_u16_png
from protocol.poses import PoseError, check_pose, pose_accuracy
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, Frame, LatestSlots, decode_frame_sample, decode_message_sample

if TYPE_CHECKING:
    import zenoh


def needs_oracle(config: MapperConfig) -> bool:
    """Whether the configured backends read simulator ground truth (ORACLE keys)."""
    from mapper.geometry.registry import ORACLE_RECONSTRUCTORS
    from mapper.perception.registry import ORACLE_BACKENDS

    p = config.perception
    return (config.geometry.backend in ORACLE_RECONSTRUCTORS or p.segmenter in ORACLE_BACKENDS
            or p.embedder in ORACLE_BACKENDS)


def reduce_nearest(image: np.ndarray, reduction: int) -> np.ndarray:
    """``image`` (H, W, ...) on the grid of its frame decoded at 1/``reduction`` (:func:`protocol.jpeg.reduced_size`):
    each output pixel takes the input pixel nearest the centre of its ``reduction`` x ``reduction`` block (an
    instance id stays an id; a partial block at the right or bottom edge takes its nearest pixel inside)."""
    if reduction == 1:
        return image
    h, w = image.shape[:2]
    ow, oh = reduced_size((w, h), reduction)
    rows = np.minimum(np.arange(oh) * reduction + reduction // 2, h - 1)
    cols = np.minimum(np.arange(ow) * reduction + reduction // 2, w - 1)
    return image[rows[:, None], cols[None, :]]


def oracle_data(msg: OracleFrame, frame_size: tuple[int, int] | None = None, reduction: int = 1,
                max_decode_bytes: int | None = None) -> OracleData:
    """Decode an OracleFrame's PNGs (raises JpegError on corrupt images, and with ``frame_size`` (width, height)
    on images of another size than their frame, before any pixel is decoded), brought to the frame's grid at
    1/``reduction`` (:func:`reduce_nearest`). A PNG cannot be decoded reduced: one whose full-size decode needs more
    than ``max_decode_bytes`` is refused unread."""

    def u16(data: bytes) -> np.ndarray:
        if max_decode_bytes is not None and frame_size is not None:
            need = PNG_DECODE_BYTES_PER_PIXEL * frame_size[0] * frame_size[1]
            if need > max_decode_bytes:
                raise JpegError(f"an ORACLE PNG of {frame_size[0]}x{frame_size[1]} needs {need / 2**20:.0f} MiB to "
                                f"decode: over {max_decode_bytes / 2**20:.0f} MiB")
        return reduce_nearest(decode_u16_png(data, expected_size=frame_size), reduction)

    # Reduced before conversion: the full-size image is never held as float32 or int32.
    depth = u16(msg.depth_png).astype(np.float32) / 1000.0 if msg.depth_png is not None else None
    ids = u16(msg.ids_png).astype(np.int32) if msg.ids_png is not None else None
    if depth is None:
        depth = np.zeros(ids.shape if ids is not None else (1, 1), dtype=np.float32)
    labels: dict[int, str] = {}
    for k, v in msg.labels.items():
        try:
            labels[int(k)] = v
        except ValueError:
            continue
    return OracleData(
        depth_m=depth, T_world_cam_true=np.asarray(msg.T_world_cam_true), instance_id=ids, labels=labels
    )


class PriorAccuracy:
    """How accurate a source's pose priors are, from the covariances its frame headers declare.

    A pose's error is taken as drift (odometry, visual-inertial tracking: it accrues with motion and is
    shared by the frames after it, so the declared covariance grows) on top of a per-frame error that
    does not accrue. The per-frame part is the smallest covariance the source has declared so far
    (elementwise over the diagonal); a source that declares a constant covariance (a motion-capture system,
    a calibration file, a recording's stated accuracy) has no drift part at all. The view gets the
    per-frame part as ``prior_rel_trans_m`` / ``prior_rel_rot_deg`` and the covariance itself, from which
    the reconstructor adds the drift between two views (the growth of the covariance between them).
    Bounded: the floors of at most ``max_sources`` sources are kept (the oldest forgotten first).
    """

    def __init__(self, max_sources: int) -> None:
        self.max_sources = max_sources
        self._floor: collections.OrderedDict[str, np.ndarray] = collections.OrderedDict()

    def fields(self, source_id: str, covariance: object) -> dict[str, object]:
        """The View fields for a frame of ``source_id`` that declared ``covariance`` (None: none declared).
        Raises :class:`PoseError` for a covariance that is not one."""
        if covariance is None:
            return {}
        C = np.asarray(covariance, dtype=np.float64)
        pose_accuracy(C, source=f"{source_id} pose covariance")  # shape, finite, >= 0
        d = np.diag(C)
        floor = self._floor.get(source_id)
        floor = d.copy() if floor is None else np.minimum(floor, d)
        self._floor[source_id] = floor
        self._floor.move_to_end(source_id)
        while len(self._floor) > self.max_sources:
            self._floor.popitem(last=False)
        acc = pose_accuracy(np.diag(floor))
        return {"prior_rel_trans_m": acc.trans_m, "prior_rel_rot_deg": acc.rot_deg, "pose_covariance": C}


class DecodeBudget:
    """Decoded pixels in flight across all sources: a frame is decoded only when its pixels fit."""

    def __init__(self, max_pixels: int) -> None:
        self.max_pixels = max_pixels
        self.in_flight = 0
        self.peak = 0
        self._lock = threading.Lock()

    def acquire(self, pixels: int) -> bool:
        """Reserve ``pixels``; False (nothing reserved) when they do not fit in the budget."""
        with self._lock:
            if self.in_flight + pixels > self.max_pixels:
                return False
            self.in_flight += pixels
            self.peak = max(self.peak, self.in_flight)
            return True

    def release(self, pixels: int) -> None:
        with self._lock:
            self.in_flight = max(0, self.in_flight - pixels)


class FrameIntake:
    """The frame path up to a View. Callbacks (``on_frame``, ``on_oracle``) run on Zenoh threads; ``ready``,
    ``decode``, ``release`` and ``view`` on the mapper's thread."""

    def __init__(self, config: MapperConfig, keys: Keys, counters: Counters, bad_input: RateLimitedLog) -> None:
        self.config, self.keys, self.counters, self.bad_input = config, keys, counters, bad_input
        lim = config.limits
        self.slots: LatestSlots[Frame] = LatestSlots(
            depth=config.ring_depth, max_keys=config.max_sources, max_bytes=lim.max_buffered_frame_bytes,
            size=lambda f: len(f.jpeg),
        )
        self.needs_oracle = needs_oracle(config)
        self._oracle: collections.OrderedDict[tuple[str, int], OracleFrame] = collections.OrderedDict()
        self._oracle_lock = threading.Lock()
        # Frames (still compressed) waiting for their ORACLE sample, with their deadline; bounded in count and bytes.
        self._pending: collections.deque[tuple[Frame, float]] = collections.deque(maxlen=2 * config.max_sources)
        self.decode_budget = DecodeBudget(lim.decode_budget_pixels)
        self.accuracy = PriorAccuracy(config.max_sources)

    def extra_counters(self) -> dict[str, float]:
        """The intake's share of the mapper's Status counters."""
        return {
            "frames_dropped": self.counters.get("frames_dropped") + self.slots.dropped,
            "sources_refused": self.slots.refused_keys,
            "sources_evicted": self.slots.evicted_keys,
            "frame_bytes_buffered": self.slots.bytes,
            "decoded_pixels_in_flight": self.decode_budget.in_flight,
            "decoded_pixels_peak": self.decode_budget.peak,
        }

    def refuse(self, reason: str, msg: str, *args: object) -> None:
        """Count a refused input under ``reason`` (and ``decode_errors`` when its image was refused unread) and
        log it (rate-limited)."""
        self.counters.add(reason)
        if reason in IMAGE_REASONS:
            self.counters.add("decode_errors")
        self.bad_input.warning(reason, msg, *args)

    def on_frame(self, sample: zenoh.Sample) -> None:
        self.counters.add("frames_in")
        try:
            self.admit(sample)
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self.refuse("frame_errors", "frame on %s failed: %s: %s", sample.key_expr, type(e).__name__, e)

    def admit(self, sample: zenoh.Sample) -> None:
        """Check a frame sample as it arrives; only an acceptable frame takes a ring slot."""
        lim = self.config.limits
        size = len(sample.payload)
        if size > lim.max_frame_bytes:  # refused before the payload is copied out of Zenoh
            self.refuse("frames_too_large", "refused a %d-byte frame on %s (limits.max_frame_bytes = %d)",
                         size, sample.key_expr, lim.max_frame_bytes)
            return
        try:
            frame = decode_frame_sample(sample)
        except (DecodeError, ValueError) as e:
            self.refuse("header_errors", "bad frame sample on %s: %s", sample.key_expr, e)
            return
        self.admit_frame(frame)

    def admit_frame(self, frame: Frame) -> None:
        """The checks of :meth:`admit` on a frame whose header decoded (``protocol.transport.decode_frame_bytes``
        makes one from a sample's bytes): replays and benchmarks go through here exactly as live frames do."""
        lim = self.config.limits
        try:
            kind, source_id = self.keys.parse_frame(frame.key)
            if source_id != frame.header.source_id or kind != frame.header.source_kind:
                raise DecodeError(f"header names {frame.header.source_id!r}, key {frame.key!r}")
        except (DecodeError, ValueError) as e:
            self.refuse("header_errors", "bad frame sample on %s: %s", frame.key, e)
            return
        h = frame.header
        problem = frame_problem(h, frame.jpeg, lim)
        if problem is not None:
            self.refuse(problem[0], "refused a frame from %s#%d: %s", h.source_id, h.seq, problem[1])
            return
        # Checked on arrival: a bad-pose frame never takes a ring slot from its source's good frames.
        checked = self._checked_pose(frame)
        if checked is not None:
            self.slots.put(checked.key, checked)

    def _checked_pose(self, frame: Frame) -> Frame | None:
        """``frame`` with its pose projected onto SO(3) when slightly off (``poses_projected``), or None
        when the pose is unusable (``frames_bad_pose``, a rate-limited warning); the frame is dropped.

        Shape and finiteness were already checked by the codec (a header failing them is a header error).
        """
        h = frame.header
        if h.T_world_cam is None:
            return frame
        try:
            checked = check_pose(h.T_world_cam, source=f"{h.source_id} frame {h.seq} pose")
        except PoseError as e:
            self.refuse("frames_bad_pose", "dropped a frame: %s", e)
            return None
        if not checked.projected:
            return frame
        self.counters.add("poses_projected")
        return dataclasses.replace(frame, header=h.model_copy(update={"T_world_cam": checked.T.tolist()}))

    def on_oracle(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode_message_sample(sample, OracleFrame)
        except DecodeError as e:
            self.refuse("oracle_errors", "bad oracle sample on %s: %s", sample.key_expr, e)
            return
        with self._oracle_lock:
            self._oracle[(msg.source_id, msg.seq)] = msg
            while len(self._oracle) > self.config.max_oracle_cache:
                self._oracle.popitem(last=False)
        if self._pending:  # a frame may be waiting for this sample: ready() need not sleep out its timeout
            self.slots.wake()

    def _take_oracle(self, frame: Frame) -> OracleFrame | None:
        with self._oracle_lock:
            return self._oracle.pop((frame.header.source_id, frame.header.seq), None)

    def reduction(self, frame: Frame) -> int:
        """The reduction ``frame`` is decoded and worked at (:func:`mapper.intake.working_reduction`; 1 for a JPEG
        whose headers do not parse: its decode fails anyway)."""
        try:
            r = working_reduction(jpeg_info(frame.jpeg), self.config.limits)
        except JpegError:
            return 1
        return 8 if r is None else r  # None was refused on arrival; 8 keeps the budget's bound

    def working_pixels(self, frame: Frame) -> int:
        """Pixels of ``frame`` decoded at its working size: what it holds of the decode budget."""
        w, h = reduced_size((frame.header.width, frame.header.height), self.reduction(frame))
        return w * h

    def decode(self, frame: Frame) -> np.ndarray | None:
        """The frame's RGB image at its working size (its pixels are held in ``decode_budget`` until
        :meth:`release`), or None."""
        h = frame.header
        lim = self.config.limits
        reduction = self.reduction(frame)
        ow, oh = reduced_size((h.width, h.height), reduction)
        if not self.decode_budget.acquire(ow * oh):
            self.refuse("frames_over_decode_budget", "no decode budget for %s#%d (%dx%d at 1/%d)",
                         h.source_id, h.seq, h.width, h.height, reduction)
            return None
        try:
            # The size is checked against the header, and the decode's memory against its limit, before any
            # pixel is decoded (no memory bombs).
            rgb = decode_jpeg(frame.jpeg, expected_size=(h.width, h.height), max_pixels=lim.max_frame_pixels,
                              min_bytes_per_mpixel=lim.min_jpeg_bytes_per_mpixel, reduction=reduction,
                              max_decode_bytes=lim.max_decode_bytes)
            if rgb.shape[:2] != (oh, ow):
                raise JpegError(f"JPEG is {rgb.shape}, header says {h.width}x{h.height} (at 1/{reduction}: {ow}x{oh})")
        except JpegError as e:
            self.release(frame)
            self.refuse("decode_errors", "bad JPEG from %s#%d: %s", h.source_id, h.seq, e)
            return None
        return rgb

    def release(self, frame: Frame) -> None:
        self.decode_budget.release(self.working_pixels(frame))

    def view(self, frame: Frame, rgb: np.ndarray, oracle: OracleFrame | None) -> View | None:
        """The :class:`View` of ``frame`` decoded as ``rgb`` (:meth:`decode`: at its working size, to which its
        intrinsics and ORACLE images are brought), or None (counted)."""
        h = frame.header
        reduction = self.reduction(frame)
        try:
            accuracy = self.accuracy.fields(h.source_id, h.pose_covariance) if h.T_world_cam is not None else {}
        except PoseError as e:
            self.refuse("frames_bad_covariance", "ignored the pose covariance of %s#%d: %s", h.source_id, h.seq, e)
            accuracy = {}
        try:
            od = (oracle_data(oracle, (h.width, h.height), reduction, self.config.limits.max_decode_bytes)
                  if oracle is not None else None)
            intrinsics = h.intrinsics.reduced(reduction) if h.intrinsics is not None else None
            return View(
                image=rgb,
                source_id=h.source_id,
                intrinsics=intrinsics,
                T_world_cam=None if h.T_world_cam is None else np.asarray(h.T_world_cam),
                pose_trusted=h.pose_trusted,
                stamp_ns=h.stamp_ns,
                seq=h.seq,
                oracle=od,
                map_always=h.map_always,
                **accuracy,  # type: ignore[arg-type]
            )
        except (ValueError, JpegError) as e:
            self.refuse("decode_errors", "unusable frame from %s#%d: %s", h.source_id, h.seq, e)
            return None

    def ready(self, timeout_s: float) -> list[tuple[Frame, OracleFrame | None]]:
        """Frames ready to process, still compressed (with their ORACLE sample when one is needed)."""
        fresh = [f for _, f in self.slots.take_all(timeout=timeout_s)]
        if not self.needs_oracle:
            return [(f, None) for f in fresh]
        now = time.monotonic()
        for f in fresh:
            if len(self._pending) == self._pending.maxlen:
                self.counters.add("frames_dropped")
            self._pending.append((f, now + self.config.oracle_wait_s))
        # The frames waiting have the same byte bound as the receive rings: the oldest go first.
        held = sum(len(f.jpeg) for f, _ in self._pending)
        while held > self.config.limits.max_buffered_frame_bytes:
            f, _ = self._pending.popleft()
            held -= len(f.jpeg)
            self.counters.add("frames_dropped")
        ready: list[tuple[Frame, OracleFrame | None]] = []
        waiting: collections.deque[tuple[Frame, float]] = collections.deque(maxlen=self._pending.maxlen)
        while self._pending:
            f, deadline = self._pending.popleft()
            o = self._take_oracle(f)
            if o is not None:
                ready.append((f, o))
            elif now >= deadline:
                self.counters.add("frames_without_oracle")
            else:
                waiting.append((f, deadline))
        self._pending = waiting
        return ready
