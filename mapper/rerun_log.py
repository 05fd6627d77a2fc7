"""Optional Rerun output of the mapper: point map, labelled boxes, edges, camera frusta with images.

``--rerun FILE.rrd`` records to a file. ``--rerun-serve`` starts the ``rerun`` CLI as a subprocess with
``--serve-grpc --bind 127.0.0.1`` (never all interfaces; ``rr.serve_*`` is deliberately not used
because it binds every interface) and streams to it; connect a viewer with
``rerun --connect rerun+http://127.0.0.1:<port>/proxy``.
"""

from __future__ import annotations

import logging
import math
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mapper.config import RerunConfig

if TYPE_CHECKING:
    from mapper.core import MapperCore

log = logging.getLogger(__name__)


def _rerun_cli() -> str:
    exe = Path(sys.executable).with_name("rerun")
    if exe.exists():
        return str(exe)
    found = shutil.which("rerun")
    if found is None:
        raise RuntimeError("the rerun CLI is not installed (pip install rerun-sdk)")
    return found


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
    rgb = cv2.cvtColor(np.uint8([[[h // 2, 200, 230]]]), cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


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
                [_rerun_cli(), "--serve-grpc", "--bind", "127.0.0.1", "--port", str(cfg.port)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,
            )
            _wait_port(cfg.port)
            url = f"rerun+http://127.0.0.1:{cfg.port}/proxy"
            sinks.append(rr.GrpcSink(url))
            log.info("Rerun live at %s (127.0.0.1 only): rerun --connect %s", url, url)
        self.rec.set_sinks(*sinks)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.step = 0

    def log(self, core: MapperCore) -> None:
        rr, rec = self._rr, self.rec
        self.step += 1
        rec.set_time("keyframe", sequence=self.step)
        pm = core.point_map(200_000)
        if len(pm.points):
            rec.log("world/points", rr.Points3D(pm.points, colors=pm.colors, radii=pm.voxel_m / 3))
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
            rec.log(path + "/image", rr.Image(img))

    def close(self) -> None:
        try:
            self.rec.flush()
            self.rec.disconnect()
        except Exception as e:  # noqa: BLE001 - closing a viewer stream must not fail shutdown
            log.debug("closing Rerun failed: %s", e)
        if self._server is not None:
            self._server.terminate()
            try:
                self._server.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._server.kill()
