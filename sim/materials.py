"""Procedural surface materials: world-space value noise, wood grain, planks, tiles, weave, speckle.

Every surface of the simulated world carries a :class:`Material`; the renderer evaluates its pattern at
the world-space hit points, so textures are consistent between views (what stereo and feature matching
need) and cost nothing to store. Everything here is pure, vectorised numpy and deterministic.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

PATTERNS: tuple[str, ...] = ("noise", "grain", "planks", "tiles", "weave", "speckle", "paint", "leaf")
"""Pattern kinds, indexed by :attr:`Material.pattern`."""


def _rgb(values: Sequence[float]) -> tuple[float, float, float]:
    r, g, b = (float(c) for c in values)
    return r, g, b


@dataclass(frozen=True)
class Material:
    """A procedural material. Colours are linear RGB in [0, 1]."""

    name: str
    pattern: str
    color1: tuple[float, float, float]
    color2: tuple[float, float, float]
    scale_m: float = 0.1
    contrast: float = 0.5

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Material:
        return cls(
            name=str(d["name"]),
            pattern=str(d["pattern"]),
            color1=_rgb(d["color1"]),
            color2=_rgb(d["color2"]),
            scale_m=float(d.get("scale_m", 0.1)),
            contrast=float(d.get("contrast", 0.5)),
        )


# ----------------------------------------------------------------------------------------------
# Colour palettes per material kind: (pattern, hue range, saturation range, value range, scale_m, contrast)
# Hues in [0, 1]; the second colour is derived (darker / shifted) from the first.
_KINDS: dict[str, tuple[str, tuple[float, float], tuple[float, float], tuple[float, float], float, float]] = {
    "wood": ("grain", (0.05, 0.10), (0.35, 0.65), (0.35, 0.75), 0.05, 0.55),
    "wood_dark": ("grain", (0.03, 0.08), (0.40, 0.70), (0.15, 0.35), 0.05, 0.5),
    "wood_floor": ("planks", (0.05, 0.10), (0.35, 0.60), (0.40, 0.70), 0.18, 0.5),
    "fabric": ("weave", (0.0, 1.0), (0.15, 0.55), (0.30, 0.80), 0.012, 0.35),
    "accent": ("weave", (0.0, 1.0), (0.45, 0.85), (0.50, 0.90), 0.010, 0.4),
    "carpet": ("weave", (0.0, 1.0), (0.20, 0.60), (0.35, 0.75), 0.02, 0.55),
    "leather": ("noise", (0.03, 0.09), (0.45, 0.75), (0.20, 0.50), 0.03, 0.3),
    "metal": ("noise", (0.55, 0.65), (0.02, 0.10), (0.55, 0.80), 0.02, 0.25),
    "plastic": ("noise", (0.0, 1.0), (0.30, 0.80), (0.40, 0.90), 0.03, 0.2),
    "white": ("noise", (0.08, 0.15), (0.00, 0.08), (0.85, 0.96), 0.05, 0.12),
    "black": ("noise", (0.55, 0.65), (0.00, 0.10), (0.06, 0.16), 0.03, 0.35),
    "ceramic": ("noise", (0.0, 1.0), (0.05, 0.45), (0.70, 0.95), 0.03, 0.18),
    "glass": ("noise", (0.25, 0.45), (0.20, 0.50), (0.30, 0.60), 0.02, 0.3),
    "window": ("noise", (0.55, 0.6), (0.15, 0.35), (0.85, 0.98), 0.4, 0.25),
    "paper": ("noise", (0.0, 1.0), (0.40, 0.85), (0.35, 0.85), 0.01, 0.35),
    "stone": ("speckle", (0.0, 0.15), (0.00, 0.20), (0.35, 0.85), 0.006, 0.6),
    "screen": ("noise", (0.58, 0.66), (0.20, 0.50), (0.05, 0.20), 0.08, 0.6),
    "plant": ("leaf", (0.22, 0.36), (0.45, 0.80), (0.22, 0.55), 0.03, 0.7),
    "soil": ("noise", (0.05, 0.09), (0.50, 0.70), (0.12, 0.25), 0.01, 0.5),
    "terracotta": ("noise", (0.02, 0.06), (0.55, 0.75), (0.45, 0.70), 0.03, 0.25),
    "fruit_red": ("noise", (0.97, 1.0), (0.70, 0.90), (0.55, 0.80), 0.02, 0.3),
    "fruit_orange": ("noise", (0.06, 0.09), (0.80, 0.95), (0.80, 0.95), 0.01, 0.25),
    "paint": ("paint", (0.0, 1.0), (0.06, 0.32), (0.70, 0.93), 0.25, 0.14),
    "ceiling": ("paint", (0.10, 0.14), (0.00, 0.04), (0.90, 0.96), 0.3, 0.06),
    "tile_floor": ("tiles", (0.0, 1.0), (0.00, 0.20), (0.55, 0.90), 0.30, 0.25),
    "tile_wall": ("tiles", (0.45, 0.62), (0.05, 0.30), (0.75, 0.95), 0.15, 0.15),
}
MATERIAL_KINDS: tuple[str, ...] = tuple(_KINDS)


def make_material(kind: str, rng: np.random.Generator, name: str | None = None) -> Material:
    """A new material of ``kind`` with a colour drawn from that kind's palette."""
    if kind not in _KINDS:
        raise ValueError(f"unknown material kind {kind!r}; known: {', '.join(_KINDS)}")
    pattern, hr, sr, vr, scale, contrast = _KINDS[kind]
    h = float(rng.uniform(*hr)) % 1.0
    s = float(rng.uniform(*sr))
    v = float(rng.uniform(*vr))
    c1 = colorsys.hsv_to_rgb(h, s, v)
    if pattern in ("grain", "planks"):
        c2 = colorsys.hsv_to_rgb(h, min(1.0, s * 1.15), v * 0.55)
    elif pattern == "tiles":
        c2 = colorsys.hsv_to_rgb(h, s * 0.3, min(1.0, v * 0.55 + 0.2))  # grout
    elif pattern == "leaf":
        c2 = colorsys.hsv_to_rgb((h + 0.04) % 1.0, s, min(1.0, v * 1.7))
    elif pattern == "weave":
        c2 = colorsys.hsv_to_rgb((h + float(rng.uniform(-0.08, 0.08))) % 1.0, s, v * 0.6)
    elif pattern == "speckle":
        c2 = colorsys.hsv_to_rgb((h + 0.5) % 1.0, s * 0.5, 1.0 - v * 0.8)
    else:
        c2 = colorsys.hsv_to_rgb(h, s, v * 0.7)
    r3 = lambda c: (round(c[0], 4), round(c[1], 4), round(c[2], 4))  # noqa: E731
    return Material(
        name=name or kind,
        pattern=pattern,
        color1=r3(c1),
        color2=r3(c2),
        scale_m=round(scale * float(rng.uniform(0.8, 1.25)), 5),
        contrast=contrast,
    )


# ----------------------------------------------------------------------------------------------
# Hashed lattice value noise.

_M1 = np.uint32(0x9E3779B1)
_M2 = np.uint32(0x85EBCA77)
_M3 = np.uint32(0xC2B2AE3D)


def _hash_u32(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    h = ix.astype(np.uint32) * _M1
    h ^= iy.astype(np.uint32) * _M2
    h ^= iz.astype(np.uint32) * _M3
    h ^= np.uint32(seed & 0xFFFFFFFF)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return h


def hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point."""
    return (_hash_u32(ix, iy, iz, seed) >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1] at points ``p`` (N, 3) (lattice spacing 1)."""
    p = np.asarray(p, dtype=np.float32)
    fl = np.floor(p)
    f = p - fl
    i = fl.astype(np.int64)
    w = f * f * (3.0 - 2.0 * f)
    ix, iy, iz = i[:, 0], i[:, 1], i[:, 2]
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    c000 = hash01(ix, iy, iz, seed)
    c100 = hash01(ix + 1, iy, iz, seed)
    c010 = hash01(ix, iy + 1, iz, seed)
    c110 = hash01(ix + 1, iy + 1, iz, seed)
    c001 = hash01(ix, iy, iz + 1, seed)
    c101 = hash01(ix + 1, iy, iz + 1, seed)
    c011 = hash01(ix, iy + 1, iz + 1, seed)
    c111 = hash01(ix + 1, iy + 1, iz + 1, seed)
    x00 = c000 + (c100 - c000) * wx
    x10 = c010 + (c110 - c010) * wx
    x01 = c001 + (c101 - c001) * wx
    x11 = c011 + (c111 - c011) * wx
    y0 = x00 + (x10 - x00) * wy
    y1 = x01 + (x11 - x01) * wy
    return y0 + (y1 - y0) * wz


def fbm(p: np.ndarray, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1]."""
    p = np.asarray(p, dtype=np.float32)
    total = np.zeros(len(p), dtype=np.float32)
    amp, norm, freq = 1.0, 0.0, 1.0
    for o in range(octaves):
        total += np.float32(amp) * value_noise(p * np.float32(freq), seed + 101 * o)
        norm += amp
        amp *= 0.5
        freq *= 2.03
    return total / np.float32(norm)


# ----------------------------------------------------------------------------------------------
# Pattern evaluation.


def _plane_coords(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-plane coordinates per point, picked by the dominant normal axis (tri-planar)."""
    a = np.abs(normals)
    dom = np.argmax(a, axis=1)
    u = np.where(dom == 0, points[:, 1], points[:, 0])
    v = np.where(dom == 2, points[:, 1], points[:, 2])
    return u, v


def _mix(c1: np.ndarray, c2: np.ndarray, t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)[:, None]
    return c1 * (1.0 - t) + c2 * t


def albedo(
    points: np.ndarray, normals: np.ndarray, material_idx: np.ndarray, materials: list[Material]
) -> np.ndarray:
    """Surface colour (N, 3) float32 in [0, 1] of each hit point under its material."""
    n = len(points)
    out = np.zeros((n, 3), dtype=np.float32)
    if n == 0 or not materials:
        return out
    c1_tab = np.array([m.color1 for m in materials], dtype=np.float32)
    c2_tab = np.array([m.color2 for m in materials], dtype=np.float32)
    sc_tab = np.array([m.scale_m for m in materials], dtype=np.float32)
    ct_tab = np.array([m.contrast for m in materials], dtype=np.float32)
    pat_tab = np.array([PATTERNS.index(m.pattern) if m.pattern in PATTERNS else 0 for m in materials])
    pat = pat_tab[material_idx]
    for k, name in enumerate(PATTERNS):
        sel = np.nonzero(pat == k)[0]
        if len(sel) == 0:
            continue
        mi = material_idx[sel]
        p = points[sel].astype(np.float32)
        nrm = normals[sel]
        c1, c2 = c1_tab[mi], c2_tab[mi]
        s = sc_tab[mi][:, None]
        ct = ct_tab[mi]
        seed = 17 * (k + 1)
        if name == "noise":
            t = fbm(p / s, 3, seed)
            col = _mix(c1, c2, 0.5 + (t - 0.5) * 2.0 * ct * 2.0)
        elif name == "paint":
            t = fbm(p / s, 3, seed)
            fine = value_noise(p / (s * 0.08), seed + 5)
            col = c1 * (1.0 + ct[:, None] * ((t - 0.5) * 1.6 + (fine - 0.5) * 0.6)[:, None])
        elif name == "grain":
            # Rings elongated along the longer horizontal world axis of the part (x or y by material id).
            axis = (mi % 2).astype(bool)
            along = np.where(axis, p[:, 0], p[:, 1])
            q = p / s
            q_str = np.stack([q[:, 0] * np.where(axis, 0.12, 1.0), q[:, 1] * np.where(axis, 1.0, 0.12),
                              q[:, 2]], axis=1)
            warp = fbm(q_str, 3, seed)
            across = np.where(axis, p[:, 1], p[:, 0]) + p[:, 2] * 0.7
            rings = 0.5 + 0.5 * np.sin((across / s[:, 0] * 1.3 + warp * 6.0) * np.pi)
            fine = value_noise(np.stack([along * 3.0, across * 120.0, p[:, 2] * 120.0], 1), seed + 3)
            col = _mix(c1, c2, ct * (rings**2) + 0.25 * fine)
        elif name == "planks":
            u, v = _plane_coords(p, nrm)
            w = s[:, 0]
            row = np.floor(v / w)
            stagger = hash01(row.astype(np.int64), np.zeros_like(row, np.int64), np.zeros_like(row, np.int64), 7)
            seg = np.floor(u / (w * 7.0) + stagger)
            jit = hash01(row.astype(np.int64), seg.astype(np.int64), np.ones_like(row, np.int64), 9)
            grain = fbm(np.stack([u * 2.0, v * 60.0, jit * 10.0], 1), 3, seed)
            fv = v / w - row
            fu = u / (w * 7.0) + stagger - seg
            seam = (fv < 0.04) | (fu < 0.006)
            t = 0.2 + 0.5 * jit + ct * (grain - 0.5) * 1.5
            col = _mix(c1, c2, t)
            col[seam] *= 0.45
        elif name == "tiles":
            u, v = _plane_coords(p, nrm)
            w = s[:, 0]
            tu, tv = np.floor(u / w), np.floor(v / w)
            fu, fv = u / w - tu, v / w - tv
            grout = (fu < 0.04) | (fv < 0.04)
            jit = hash01(tu.astype(np.int64), tv.astype(np.int64), np.zeros_like(tu, np.int64), 11)
            t = fbm(p / 0.02, 2, seed)
            col = c1 * (1.0 + ct[:, None] * ((jit - 0.5) * 1.2 + (t - 0.5) * 0.8)[:, None])
            col[grout] = c2[grout]
        elif name == "weave":
            u, v = _plane_coords(p, nrm)
            w = s[:, 0]
            thread = 0.5 + 0.25 * (np.sin(u / w * np.pi) + np.sin(v / w * np.pi))
            coarse = fbm(p / (w[:, None] * 12.0), 3, seed)
            col = _mix(c1, c2, ct * (0.6 * thread + 1.2 * (coarse - 0.5)) + 0.2)
        elif name == "speckle":
            t = value_noise(p / s, seed)
            base = fbm(p / (s * 10.0), 2, seed + 1)
            col = c1 * (0.8 + 0.4 * base)[:, None]
            spots = t > 0.78
            col[spots] = _mix(col[spots], c2[spots], ct[spots])
        elif name == "leaf":
            t = fbm(p / s, 3, seed)
            cells = value_noise(p / (s * 0.35), seed + 2)
            col = _mix(c1, c2, (t - 0.35) * 2.0 * ct + (cells > 0.6) * 0.35)
        else:  # pragma: no cover - PATTERNS is closed
            col = c1
        out[sel] = col
    np.clip(out, 0.0, 1.0, out=out)
    return out
