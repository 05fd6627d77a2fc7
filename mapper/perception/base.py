"""2D perception contract: a Segmenter finds instance masks, an Embedder describes and labels them.

Both are ``typing.Protocol``s with frozen dataclass outputs. Backends live in sibling modules and are
built through :mod:`mapper.perception.registry` (heavy imports only inside the chosen backend).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from mapper.geometry.contract import View


@dataclass(frozen=True)
class Mask2D:
    """One instance mask of an image.

    ``mask`` is (H, W) bool at the image's resolution. ``hint_label`` is set only by backends that
    already know the class (the ``sim`` ORACLE); ``instance_key`` is a backend-specific id (the oracle's
    object id, a segment index) kept for logs.
    """

    mask: np.ndarray
    instance_key: int = 0
    hint_label: str | None = None
    score: float = 1.0


@dataclass(frozen=True)
class Detection:
    """A labelled, described 2D detection: the input of 3D fusion.

    ``descriptor`` is a unit float32 vector (its dimension depends on the embedder); ``confidence`` is
    the label's confidence in [0, 1]; ``alternatives`` lists other ``(label, score)`` candidates.
    """

    mask: np.ndarray
    label: str
    confidence: float
    descriptor: np.ndarray
    alternatives: tuple[tuple[str, float], ...] = field(default_factory=tuple)
    instance_key: int = 0


@dataclass(frozen=True)
class ViewGeometry:
    """A view's reconstruction at the geometry's resolution (h, w), which may be below the image's.

    points_world: (h, w, 3) float32 metres, world z up; depth_m: (h, w) float32 z-depth (0 = none);
    confidence: (h, w) float32 in [0, 1].
    """

    points_world: np.ndarray
    depth_m: np.ndarray
    confidence: np.ndarray


class Segmenter(Protocol):
    """Finds instance masks in one view."""

    name: str
    description: str

    def segment(self, view: View, geometry: ViewGeometry | None = None) -> list[Mask2D]:
        """Masks of ``view.image``; the view's reconstruction may guide class-agnostic backends (depth
        edges, plane removal). Masks may come at the geometry's resolution instead of the image's."""
        ...


class Embedder(Protocol):
    """Describes and labels masks of one view."""

    name: str
    description: str

    def embed(self, view: View, masks: Sequence[Mask2D]) -> list[Detection]:
        """One :class:`Detection` per mask, in order (a backend may drop masks it cannot describe)."""
        ...


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to unit length as float32 (zero stays zero)."""
    v = np.asarray(v, dtype=np.float32).reshape(-1)
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def label_descriptor(label: str, dim: int = 128) -> np.ndarray:
    """A deterministic unit vector for a label text (character-trigram hashing).

    Equal labels give equal vectors, different labels nearly orthogonal ones, and labels sharing
    words partly similar ones: a weight-free stand-in for a text embedding.
    """
    import zlib

    v = np.zeros(dim, dtype=np.float32)
    text = f"  {label.strip().lower()}  "
    for i in range(len(text) - 2):
        h = zlib.crc32(text[i : i + 3].encode("utf-8"))
        v[h % dim] += 1.0 if (h >> 16) & 1 else -1.0
    return unit(v)
