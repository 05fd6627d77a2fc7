"""Evidence for absence: what a keyframe's measured depth says about each node it should see (pure: no I/O).

A node whose points project into a keyframe, in range and well inside the image, is judged pixel by pixel at
the depth map's resolution, against the nearest of its own points there (its front surface in that view):

- the keyframe's confident depth is nearer than that surface by more than the margin: something stands in
  front (a passer-by, another object). Occluded pixels say nothing about the node;
- it is farther by more than the margin: the camera sees *through* the place the node occupies (the floor
  behind it, the wall): free;
- within the margin: a surface where the node is (the object, possibly undetected): there;
- no confident depth: unknown (stereo gives none on textureless surfaces; none of that counts).

A view is evidence of absence (``FREE``) only when the node covers enough pixels to be detected at all, most of
its pixels have confident depth, few are occluded and most of the unoccluded ones are free. "Few occluded" has
two limits when the keyframe says where people are (2D perception's people, ``KeyframeView.people``): few
pixels hidden by a person (``max_occluded``: a passer-by in front is no evidence; a pixel of a person at the
node's depth counts too, as occluded and never as the node's surface), and at most
``max_occluded_static`` hidden by anything (the furniture in front of a dining chair hides half of it from a
wall camera; the half in sight still needs ``min_pixels`` pixels). When it does not say, every occluder might be
a person (``max_occluded`` for all). It says the node
is ``THERE`` when most of its unoccluded pixels show a surface at its depth, and ``MIXED`` when the view could
judge (enough pixels, known, unoccluded) but neither kind is most of them: a low box taken off the floor of a
camera looking down leaves floor within the margin of its lower half, and a neighbour moved into its place
leaves a surface there. Anything else is ``UNKNOWN``. The margin grows with depth (estimated depth errs by a
fraction of it). See ``mapper.fusion.FusionConfig.absence_*``
for the thresholds and ``ObjectMap.integrate`` for how verdicts add up to a retirement.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from mapper.association import KeyframeView
from protocol.poses import invert, project


class Verdict(Enum):
    """What one keyframe says about one node it should see."""

    UNKNOWN = 0  # out of view, too small, too far, occluded or without confident depth: no evidence
    FREE = 1  # the keyframe sees through where the node stands: evidence that it is gone
    THERE = 2  # the keyframe sees a surface where the node stands: it is (still) there
    MIXED = 3  # it could judge, but saw through part and a surface at the rest: no evidence from depth alone


@dataclass(frozen=True)
class AbsenceParams:
    """Thresholds of :func:`judge` (the ``absence_*`` fields of ``FusionConfig``)."""

    max_range_m: float = 6.0  # nodes farther from the camera than this are not judged
    min_pixels: int = 20  # a node covering fewer depth pixels could not have been detected there
    min_in_view: float = 0.6  # fraction of the node's points that must project inside the image
    min_known: float = 0.5  # fraction of its pixels that must have confident depth
    max_occluded: float = 0.3  # more of its pixels occluded (by a person, or by anything when unknown): no verdict
    max_occluded_static: float = 0.7  # more of its pixels occluded by anything (people known): no verdict
    min_free: float = 0.7  # fraction of the unoccluded known pixels that must be free for FREE
    margin_m: float = 0.1  # depth margin, metres ...
    margin_rel: float = 0.05  # ... plus this fraction of the node's depth
    max_points: int = 600  # the node's points are thinned to at most this many (fixed stride)
    window_px: int = 1  # a pixel's depth is the nearest confident depth within this many pixels (nearest_depth)

    def too_hidden(self, n: int, occluded: int, by_people: int | None, min_left: int) -> bool:
        """Whether too much of a node's ``n`` pixels (or points) is hidden for a verdict: ``occluded`` by
        anything, ``by_people`` of them by people (None: not known, so any occluder might be a person); with
        people known, ``min_left`` must stay in sight. See the module docstring."""
        if by_people is None:
            return occluded > self.max_occluded * n
        return (by_people > self.max_occluded * n or occluded > self.max_occluded_static * n
                or n - occluded < min_left)


@dataclass(frozen=True)
class Judgement:
    """A verdict with the pixel counts behind it (for logs and tests)."""

    verdict: Verdict
    pixels: int = 0
    known: int = 0
    occluded: int = 0
    free: int = 0
    there: int = 0


def nearest_depth(view: KeyframeView, window_px: int) -> KeyframeView:
    """``view`` with each pixel's depth the nearest confident depth within ``window_px`` pixels (a min filter;
    unknown pixels take their neighbours'). A thin object (a lamp's pole, a chair's leg) covers a pixel or two,
    and estimated depth there is often the background's: seeing through it needs the whole neighbourhood
    beyond, or every thin object in view would look absent."""
    if window_px <= 0:
        return view
    import cv2

    d = np.where(np.isfinite(view.depth_m) & (view.depth_m > 0), view.depth_m, np.inf).astype(np.float32)
    k = 2 * window_px + 1
    near = cv2.erode(d, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return KeyframeView(view.K, view.T_world_cam, np.where(np.isfinite(near), near, 0.0).astype(np.float32),
                        view.people)


def boxes_out_of_view(view: KeyframeView, lo: np.ndarray, hi: np.ndarray, max_range_m: float,
                      T_cam_world: np.ndarray | None = None) -> np.ndarray:
    """(N,) whether no point of each axis-aligned box ``lo``..``hi`` (N, 3, world) can count in :func:`judge` of
    ``view``: all lie behind the camera's near limit, beyond one image border, or farther than ``max_range_m``
    along its axis; then the verdict on any points inside the box is ``UNKNOWN``. Each test is linear in the
    point, so a box's corners decide it; only a margin far above rounding (a millionth of the scale) counts, so a
    box at a limit is left to :func:`judge`. ``T_cam_world``: ``invert(view.T_world_cam)`` when the caller has
    it."""
    lo, hi = np.asarray(lo, np.float64).reshape(-1, 3), np.asarray(hi, np.float64).reshape(-1, 3)
    h, w = view.depth_m.shape
    T = invert(view.T_world_cam) if T_cam_world is None else T_cam_world
    pick = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], bool)  # (8, 3): hi where set
    corners = np.where(pick[None], hi[:, None, :], lo[:, None, :])  # (N, 8, 3)
    p = corners @ T[:3, :3].T + T[:3, 3]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    K = np.asarray(view.K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # judge counts a point when z > 0.05 and 0 <= u < w, 0 <= v < h, u = fx x / z + cx: for z > 0 these are
    # signs of linear functions of the point (u z = fx x + cx z); and its median z must be within range
    tests = np.stack([z - 0.05, fx * x + cx * z, (w - cx) * z - fx * x, fy * y + cy * z, (h - cy) * z - fy * y,
                      max_range_m - z])  # (6, N, 8)
    coeffs = 1.0 + abs(fx) + abs(fy) + abs(cx) + abs(cy) + w + h + abs(max_range_m)
    scale = coeffs * (1.0 + np.abs(p).max(axis=(1, 2)))  # (N,)
    return np.any(tests.max(axis=2) < -1e-6 * scale, axis=0)


def judge(view: KeyframeView, points_world: np.ndarray, params: AbsenceParams,
          T_cam_world: np.ndarray | None = None) -> Judgement:
    """What ``view`` (a keyframe's camera and confident depth, 0 where unknown; :func:`nearest_depth` of it, as
    ``ObjectMap.absence_verdicts`` passes it) says about a node made of ``points_world`` (N, 3): see the module
    docstring. ``T_cam_world``: ``invert(view.T_world_cam)`` when the caller has it (one per view)."""
    pts = np.asarray(points_world, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return Judgement(Verdict.UNKNOWN)
    pts = pts[:: max(1, -(-len(pts) // params.max_points))]
    h, w = view.depth_m.shape
    if T_cam_world is None:
        T_cam_world = invert(view.T_world_cam)
    p = pts @ np.ascontiguousarray(T_cam_world[:3, :3].T) + T_cam_world[:3, 3]
    uv, z = project(view.K, p)
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (z > 0.05) & np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if int(inside.sum()) < params.min_in_view * len(pts) or float(np.median(z[inside])) > params.max_range_m:
        return Judgement(Verdict.UNKNOWN)
    pix = row[inside].astype(np.intp) * w + col[inside].astype(np.intp)
    order = np.lexsort((z[inside], pix))  # per pixel, its nearest point first
    pix_sorted = pix[order]
    first = np.ones(len(pix_sorted), bool)
    first[1:] = pix_sorted[1:] != pix_sorted[:-1]
    px = pix_sorted[first]
    front = z[inside][order][first]  # the node's nearest surface at each pixel it covers
    n = len(px)
    if n < params.min_pixels:
        return Judgement(Verdict.UNKNOWN, pixels=n)
    d = view.depth_m.reshape(-1)[px].astype(np.float64)
    known = np.isfinite(d) & (d > 0)
    margin = params.margin_m + params.margin_rel * front
    occluded = known & (d < front - margin)
    free = known & (d > front + margin)
    there = known & ~occluded & ~free
    k, o, f, t = int(known.sum()), int(occluded.sum()), int(free.sum()), int(there.sum())
    by_people = None
    if view.people is not None:
        # A person in front of the place, or standing in it (people walk through furniture in a simulator, and
        # stand right at it in a room), hides it: such pixels are occluded, never the node's own surface.
        person = known & ~free & view.people.reshape(-1)[px]
        by_people = int(person.sum())
        o, t = int((occluded | person).sum()), int((there & ~person).sum())
    verdict = Verdict.UNKNOWN
    if k >= params.min_known * n and not params.too_hidden(n, o, by_people, params.min_pixels) and f + t > 0:
        if f >= params.min_free * (f + t):
            verdict = Verdict.FREE
        elif t >= params.min_free * (f + t):
            verdict = Verdict.THERE
        else:
            verdict = Verdict.MIXED
    return Judgement(verdict, pixels=n, known=k, occluded=o, free=f, there=t)
