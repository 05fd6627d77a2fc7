"""CPU renderer of the embedded world: one ray per pixel through a pinhole camera, Embree intersections.

``Renderer(scene).render(intrinsics, T_world_cam)`` returns RGB (procedural textures, two directional
lights plus ambient), z-depth in metres and instance ids (0 = structure, -1 = nothing, k = object id).
All meshes are merged into one triangle set at construction, so a frame is one batched ray cast
followed by vectorised shading at the hit points.

Two ray-casting backends: ``embree`` (embreex, the Embree binding trimesh uses; default, faster on one
core in our measurements) and ``open3d`` (``RaycastingScene``). ``benchmark()`` measures both.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from protocol.messages import Intrinsics
from sim.materials import albedo

_LIGHTS = (
    (np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0]), 0.45),
    (np.array([-0.6, -0.75, 0.35]) / np.linalg.norm([-0.6, -0.75, 0.35]), 0.22),
)
_AMBIENT = 0.38


@dataclass(frozen=True, eq=False)
class RenderOutput:
    """One rendered frame: ``rgb`` (H,W,3) uint8, ``depth_m`` (H,W) float32 z-depth (0 = no hit),
    ``instance_id`` (H,W) int32 (0 structure, -1 no hit, k >= 1 object id)."""

    rgb: np.ndarray
    depth_m: np.ndarray
    instance_id: np.ndarray


class RayCaster(Protocol):
    name: str

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays ``(N,3)``: (t in units of the direction length, inf if none; triangle, -1)."""
        ...


class EmbreeCaster:
    name = "embree"

    def __init__(self, triangles: np.ndarray):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self._scene, np.ascontiguousarray(triangles, dtype=np.float32))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(dirs, dtype=np.float32)
        res = self._scene.run(o, d, output=1)
        prim = np.asarray(res["primID"], dtype=np.int64)
        t = np.where(prim >= 0, res["tfar"], np.inf).astype(np.float64)
        return t, np.where(prim >= 0, prim, -1)


class Open3DCaster:
    name = "open3d"

    def __init__(self, triangles: np.ndarray, nthreads: int = 1):
        import open3d as o3d

        self._o3d = o3d
        self._nthreads = nthreads
        v = np.ascontiguousarray(triangles.reshape(-1, 3), dtype=np.float32)
        f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
        self._scene = o3d.t.geometry.RaycastingScene()
        cpu = o3d.core.Device("CPU:0")
        self._scene.add_triangles(o3d.core.Tensor(v, o3d.core.float32, cpu), o3d.core.Tensor(f, o3d.core.uint32, cpu))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        core = self._o3d.core
        res = self._scene.cast_rays(core.Tensor(rays, core.float32, core.Device("CPU:0")), nthreads=self._nthreads)
        t = res["t_hit"].numpy().astype(np.float64)
        prim = res["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        return np.where(hit, t, np.inf), np.where(hit, prim, -1)


BACKENDS = {"embree": EmbreeCaster, "open3d": Open3DCaster}


class Renderer:
    """Renders a :class:`sim.scene.Scene`; the ray-casting structure is built once and cached here."""

    def __init__(self, scene: Any, backend: str = "embree", background_rgb: tuple[int, int, int] = (0, 0, 0)):
        if backend not in BACKENDS:
            raise ValueError(f"unknown ray-casting backend {backend!r}; choose from {list(BACKENDS)}")
        self.scene = scene
        tris = [np.asarray(scene.structure.triangles, np.float64)]
        inst = [np.zeros(len(scene.structure.faces), np.int32)]
        mats = [np.asarray(scene.structure_face_material, np.int32)]
        for o in scene.objects:
            tris.append(np.asarray(o.mesh.triangles, np.float64))
            inst.append(np.full(len(o.mesh.faces), o.obj_id, np.int32))
            fm = o.face_material if o.face_material is not None else np.zeros(len(o.mesh.faces), np.int32)
            mats.append(np.asarray(fm, np.int32))
        self.triangles = np.concatenate(tris).astype(np.float32)
        self.face_instance = np.concatenate(inst)
        self.face_material = np.concatenate(mats)
        e1 = self.triangles[:, 1] - self.triangles[:, 0]
        e2 = self.triangles[:, 2] - self.triangles[:, 0]
        n = np.cross(e1.astype(np.float64), e2.astype(np.float64))
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        self.face_normals = (n / np.maximum(ln, 1e-20)).astype(np.float32)
        self.caster: RayCaster = BACKENDS[backend](self.triangles)
        self.background = np.array(background_rgb, np.uint8)
        self._dirs_cache: dict[tuple, np.ndarray] = {}

    @property
    def backend(self) -> str:
        return self.caster.name

    def _cam_dirs(self, K: Intrinsics) -> np.ndarray:
        key = (K.width, K.height, K.fx, K.fy, K.cx, K.cy)
        d = self._dirs_cache.get(key)
        if d is None:
            u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
            d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
            if len(self._dirs_cache) >= 8:
                self._dirs_cache.pop(next(iter(self._dirs_cache)))
            self._dirs_cache[key] = d
        return d

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits of world rays: (t, instance id: 0 structure, k object, -1 none)."""
        t, prim = self.caster.cast(np.asarray(origins, np.float64), np.asarray(dirs, np.float64))
        inst = np.where(prim >= 0, self.face_instance[np.maximum(prim, 0)], -1).astype(np.int32)
        return t, inst

    def render(self, intrinsics: Intrinsics, T_world_cam: np.ndarray, overlay: Overlay | None = None) -> RenderOutput:
        """Render one frame from camera pose ``T_world_cam`` (OpenCV axes, see protocol.poses).

        ``overlay``: moving geometry drawn into the same frame (:class:`sim.people.PeopleLayer`): each ray keeps the
        nearer of its hits in this scene and in the overlay, so a passer-by occludes what is behind it in RGB, depth
        and instance ids alike. Without one the frame is exactly the scene's."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("T_world_cam must be a finite 4x4 pose")
        K = intrinsics
        d_cam = self._cam_dirs(K)
        # Unnormalised directions with unit z in the camera frame: the hit parameter t is the z-depth.
        d_world = d_cam @ T[:3, :3].T
        origin = T[:3, 3]
        origins = np.broadcast_to(origin, d_world.shape)
        t, prim = self.caster.cast(origins, d_world)
        n_pix = K.width * K.height
        rgb = np.empty((n_pix, 3), np.uint8)
        rgb[:] = self.background
        depth = np.zeros(n_pix, np.float32)
        inst = np.full(n_pix, -1, np.int32)
        hit = prim >= 0
        if overlay is not None:
            t_o, prim_o = overlay.caster.cast(origins, d_world)
            front = (prim_o >= 0) & (t_o < t)
            hit &= ~front
            _shade_hits(front, t_o, prim_o, origin, d_world, overlay.face_instance, overlay.face_normals,
                        overlay.face_material, overlay.materials, rgb, depth, inst)
        _shade_hits(hit, t, prim, origin, d_world, self.face_instance, self.face_normals, self.face_material,
                    self.scene.materials, rgb, depth, inst)
        return RenderOutput(
            rgb=rgb.reshape(K.height, K.width, 3),
            depth_m=depth.reshape(K.height, K.width),
            instance_id=inst.reshape(K.height, K.width),
        )


class Overlay(Protocol):
    """Moving geometry :meth:`Renderer.render` draws over a scene: a ray caster over its own triangles with each
    face's instance id, unit normal and material (an index into ``materials``)."""

    caster: RayCaster
    face_instance: np.ndarray
    face_normals: np.ndarray
    face_material: np.ndarray
    materials: list[Any]


def _shade_hits(hit: np.ndarray, t: np.ndarray, prim: np.ndarray, origin: np.ndarray, d_world: np.ndarray,
                face_instance: np.ndarray, face_normals: np.ndarray, face_material: np.ndarray, materials: list[Any],
                rgb: np.ndarray, depth: np.ndarray, inst: np.ndarray) -> None:
    """Write depth, instance id and shaded colour of the rays ``hit`` selects (first hits ``t``, triangles
    ``prim``) into the flat frame buffers."""
    depth[hit] = t[hit]
    ph = prim[hit]
    inst[hit] = face_instance[ph]
    if hit.any():
        pts = origin + d_world[hit] * t[hit][:, None]
        nrm = face_normals[ph].astype(np.float64)
        facing = np.einsum("ij,ij->i", nrm, d_world[hit]) > 0
        nrm[facing] *= -1.0
        col = albedo(pts, nrm, face_material[ph], materials)
        shade = np.full(len(pts), _AMBIENT)
        for L, w in _LIGHTS:
            shade += w * np.clip(nrm @ L, 0.0, None)
        # a little distance falloff reads as indoor lighting and separates depth layers
        shade *= 1.0 / (1.0 + 0.025 * t[hit])
        rgb[hit] = np.clip(col * shade[:, None] * 255.0, 0, 255).astype(np.uint8)


def benchmark(scene: Any, intrinsics: Intrinsics, poses: list[np.ndarray], backends: tuple[str, ...] = ("embree",
              "open3d")) -> dict[str, dict[str, float]]:
    """Milliseconds per frame (wall mean and best, process CPU time) and ray-cast-only wall time per backend
    over ``poses``. Open3D runs with one thread so both backends are compared on one core."""
    out: dict[str, dict[str, float]] = {}
    for name in backends:
        t0 = time.perf_counter()
        r = Renderer(scene, backend=name)
        build_ms = (time.perf_counter() - t0) * 1e3
        r.render(intrinsics, poses[0])  # warm-up (direction cache)
        times, cpu_times, cast_times = [], [], []
        for T in poses:
            t0, c0 = time.perf_counter(), time.process_time()
            r.render(intrinsics, T)
            times.append(time.perf_counter() - t0)
            cpu_times.append(time.process_time() - c0)
            d = r._cam_dirs(intrinsics) @ np.asarray(T)[:3, :3].T
            o = np.broadcast_to(np.asarray(T)[:3, 3], d.shape)
            t0 = time.perf_counter()
            r.caster.cast(o, d)
            cast_times.append(time.perf_counter() - t0)
        out[name] = {
            "build_ms": build_ms,
            "frame_ms_mean": 1e3 * float(np.mean(times)),
            "frame_ms_best": 1e3 * float(np.min(times)),
            # CPU time of this process: what one frame costs on one core, less sensitive to other load
            "frame_cpu_ms_mean": 1e3 * float(np.mean(cpu_times)),
            "raycast_ms_mean": 1e3 * float(np.mean(cast_times)),
        }
    return out
