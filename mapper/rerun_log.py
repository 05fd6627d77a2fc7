"""Optional Rerun output of the mapper: point map, labelled boxes, edges, camera frusta with images.

``--rerun FILE.rrd`` records to a file. ``--rerun-serve`` starts the ``rerun`` viewer binary as a child
process bound to 127.0.0.1 only (``rr.serve_*`` is deliberately not used: it binds every interface)
and streams to it: connect a desktop viewer with ``rerun --connect rerun+http://127.0.0.1:<port>/proxy``;
with ``rerun.web_port`` set it also hosts the web viewer (``http://127.0.0.1:<web_port>``; from another
machine use an SSH tunnel). The child runs in its own process group, gets SIGKILL if the mapper dies
(Linux), is stopped with the mapper, and has Rerun's telemetry turned off (loopback only).

Size: the point map is logged as deltas (only voxels not logged before, as numbered parts; after
``point_parts`` parts the whole map is logged once afresh) and images are small JPEGs, so a recording
grows with the map and the number of keyframes (a few KB per keyframe for boxes and the image), not with
the map size times the keyframes. The served stream keeps at most ``server_memory_limit`` for late viewers.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mapper.config import RerunConfig
from protocol.runtime import kill_with_parent

if TYPE_CHECKING:
    from mapper.core import MapperCore

log = logging.getLogger(__name__)


def _rerun_cli() -> str:
    """The rerun viewer binary itself (the ``rerun`` script is a Python wrapper whose child would be
    orphaned when only the wrapper is stopped), else whatever ``rerun`` is on the PATH."""
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).with_name("rerun")
        if binary.exists():
            return str(binary)
    except ImportError:
        pass
    exe = Path(sys.executable).with_name("rerun")
    if exe.exists():
        return str(exe)
    found = shutil.which("rerun")
    if found is None:
        raise RuntimeError("the rerun CLI is not installed (pip install rerun-sdk)")
    return found


def server_command(cfg: RerunConfig) -> list[str]:
    """The rerun command line of the served viewer: loopback only, memory-bounded."""
    cmd = [_rerun_cli(), "--bind", "127.0.0.1", "--port", str(cfg.port),
           "--server-memory-limit", cfg.server_memory_limit]
    if cfg.web_port is not None:
        return [*cmd, "--serve-web", "--web-viewer-port", str(cfg.web_port)]
    return [*cmd, "--serve-grpc"]


def _wait_port(port: int, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise RuntimeError(f"rerun server did not open 127.0.0.1:{port}")


def _color(label: str) -> tuple[int, int, int]:
    import zlib

    h = zlib.crc32(label.encode()) % 360
    rgb = cv2.cvtColor(np.array([[[h // 2, 200, 230]]], dtype=np.uint8), cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


class PointParts:
    """Which voxels of a growing point map a recording does not hold yet (pure bookkeeping, no Rerun).

    ``take(keys)`` returns the mask of ``keys`` (int64 voxel keys) to log as the next part, and whether to clear
    the parts logged so far first: every ``max_parts`` parts the whole map is logged afresh, which also drops
    voxels the map has since evicted. Shared by the mapper's own recording and ``argus demo``'s.
    """

    def __init__(self, max_parts: int) -> None:
        self.max_parts = max_parts
        self.logged = np.zeros(0, dtype=np.int64)  # voxel keys already in the recording (sorted)
        self.parts = 0

    def take(self, keys: np.ndarray) -> tuple[np.ndarray, bool]:
        """(mask of the keys to log now, whether to clear the earlier parts first); an all-False mask: nothing."""
        keys = np.asarray(keys, dtype=np.int64)
        new = ~np.isin(keys, self.logged)
        if not new.any():
            return new, False
        refresh = self.parts >= self.max_parts
        if refresh:
            self.logged, self.parts = np.zeros(0, dtype=np.int64), 0
            new[:] = True
        self.logged = np.union1d(self.logged, keys[new])
        self.parts += 1
        return new, refresh

    @property
    def part_name(self) -> str:
        """The entity name of the part :meth:`take` just handed out."""
        return f"part{self.parts - 1}"


class RerunLogger:
    """Logs the mapper's state after each keyframe."""

    def __init__(self, cfg: RerunConfig) -> None:
        import rerun as rr

        self.cfg = cfg
        self._rr = rr
        self._server: subprocess.Popen[bytes] | None = None
        self.rec = rr.RecordingStream(application_id="argus-mapper")
        sinks: list[Any] = []
        if cfg.file is not None:
            Path(cfg.file).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(cfg.file)))
        if cfg.serve:
            self._server = subprocess.Popen(
                server_command(cfg),
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false"},
                start_new_session=True,
                preexec_fn=kill_with_parent(),
            )
            try:
                _wait_port(cfg.port)
            except RuntimeError:
                self._stop_server()
                raise
            url = f"rerun+http://127.0.0.1:{cfg.port}/proxy"
            sinks.append(rr.GrpcSink(url))
            log.info("Rerun live at %s (127.0.0.1 only): rerun --connect %s", url, url)
            if cfg.web_port is not None:
                log.info("Rerun web viewer (127.0.0.1 only): http://127.0.0.1:%d/?url=%s", cfg.web_port, url)
        self.rec.set_sinks(*sinks)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.step = 0
        self._points = PointParts(cfg.point_parts)

    def _log_points(self, core: MapperCore) -> None:
        """Log the voxels not logged before as one more part; every ``point_parts`` parts, the whole map."""
        rr, rec = self._rr, self.rec
        with core.lock:
            vox = core.voxels
            keys, pts, cols, voxel_m = vox.keys.copy(), vox.points(), vox.colors(), vox.voxel_m
        new, refresh = self._points.take(keys)
        if not new.any():
            return
        if refresh:
            rec.log("world/points", rr.Clear(recursive=True))
        rec.log(f"world/points/{self._points.part_name}",
                rr.Points3D(pts[new], colors=cols[new], radii=voxel_m / 3))

    def log(self, core: MapperCore) -> None:
        rr, rec = self._rr, self.rec
        self.step += 1
        rec.set_time("keyframe", sequence=self.step)
        self._log_points(core)
        nodes = core.nodes()
        if nodes:
            rec.log(
                "world/objects",
                rr.Boxes3D(
                    centers=[n.box.center for n in nodes],
                    sizes=[n.box.extent for n in nodes],
                    rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), angle=n.box.yaw_rad) for n in nodes],
                    labels=[f"{n.label} ({n.node_id})" for n in nodes],
                    colors=[_color(n.label) for n in nodes],
                    show_labels=True,  # the viewer hides labels of a batch with many instances otherwise
                ),
            )
            centre = {n.node_id: n.centroid for n in nodes}
            edges = [e for e in core.snapshot().edges if e.subject_id in centre and e.object_id in centre]
            if edges:
                rec.log(
                    "world/edges",
                    rr.LineStrips3D(
                        [[centre[e.subject_id], centre[e.object_id]] for e in edges],
                        labels=[e.predicate for e in edges],
                        radii=0.005,
                    ),
                )
        self._log_rooms(core)
        last = core.last
        if last is not None:
            v = last.view
            path = f"world/cameras/{v.source_id}"
            T = last.T_world_cam
            rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            h, w = v.image.shape[:2]
            ow = min(self.cfg.image_width, w)
            oh = max(1, round(h * ow / w))
            img = cv2.resize(v.image, (ow, oh), interpolation=cv2.INTER_AREA)
            if v.intrinsics is not None:
                k = v.intrinsics.scaled(ow, oh)
                f, pp = (k.fx, k.fy), (k.cx, k.cy)
            else:
                f, pp = (ow / 2 / math.tan(math.radians(35)),) * 2, (ow / 2, oh / 2)
            rec.log(path + "/image", rr.Pinhole(focal_length=f, principal_point=pp, resolution=(ow, oh),
                                                camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3))
            rec.log(path + "/image", rr.Image(img).compress(jpeg_quality=self.cfg.jpeg_quality))

    def _log_rooms(self, core: MapperCore) -> None:
        """Room outlines on the floor under the objects, labelled with their kind and id, and the doorways."""
        layer = core.room_layer()
        if layer is None:
            return
        rr, rec = self._rr, self.rec
        if not layer.rooms:
            rec.log("world/rooms", rr.Clear(recursive=True))
            return
        strips = [[(x, y, r.floor_z_m + 0.02) for x, y in [*r.polygon, r.polygon[0]]] for r in layer.rooms if r.polygon]
        named = [r for r in layer.rooms if r.polygon]
        rec.log("world/rooms/outlines", rr.LineStrips3D(
            strips, labels=[f"{r.label} ({r.room_id}, {r.label_confidence:.2f})" for r in named],
            colors=[_color(r.label) for r in named], radii=0.02, show_labels=True))
        doors = [e for e in layer.edges if e.predicate == "connects" and e.position is not None]
        z = {r.room_id: r.floor_z_m for r in layer.rooms}
        if doors:
            rec.log("world/rooms/doorways", rr.Points3D(
                [(e.position[0], e.position[1], z.get(e.subject_id, 0.0) + 0.05) for e in doors if e.position],
                labels=[f"{e.subject_id} - {e.object_id}" for e in doors], radii=0.08))
        else:
            rec.log("world/rooms/doorways", rr.Clear(recursive=False))

    def close(self) -> None:
        try:
            self.rec.flush()
            self.rec.disconnect()
        except Exception as e:  # noqa: BLE001 - closing a viewer stream must not fail shutdown
            log.debug("closing Rerun failed: %s", e)
        self._stop_server()

    def _stop_server(self) -> None:
        """SIGTERM the server's process group, SIGKILL it after 5 s: nothing keeps holding the port."""
        if self._server is None:
            return
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(self._server.pid, sig)
            except ProcessLookupError:
                break
            try:
                self._server.wait(timeout=5)
                break
            except subprocess.TimeoutExpired:
                continue
        self._server = None
