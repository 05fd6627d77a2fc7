"""``type = "sim"``: a fixed camera in the embedded simulated world (a scene from ``sim/``).

The scene is generated from ``(family, seed)``; ``n_cameras`` cameras are placed high in room
corners and this source is camera ``camera_index`` of them. The world is static, so the view is
rendered once and re-sent (``rerender = true`` renders every frame, e.g. to load-test). With
``oracle = true`` the source also hands out the ORACLE ground truth (true pose, instance ids, depth)
that the node publishes as an OracleFrame beside each frame. The simulator is imported only when
the source is created, so the other sources never pull it in.
"""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from edge_camera.sources.base import Grab, OracleCapture, SourceBase, SourceConfig, SourceConfigError
from protocol.messages import Intrinsics


class Config(SourceConfig):
    type: Literal["sim"] = Field(default="sim", description="fixed camera in the simulated world")
    family: Literal["apartment", "furnished_room", "apartment_large"] = Field(
        default="apartment", description="scene family"
    )
    seed: int = Field(default=0, ge=0, description="scene seed")
    n_cameras: int = Field(default=1, ge=1, le=3, description="cameras placed in the scene (1..3)")
    camera_index: int = Field(default=0, ge=0, le=2, description="which placed camera this source is")
    width: int = Field(default=640, gt=0, le=4096, description="render width, pixels")
    height: int = Field(default=480, gt=0, le=4096, description="render height, pixels")
    hfov_deg: float = Field(default=90.0, gt=1, lt=179, description="horizontal field of view, degrees")
    rate_hz: float = Field(default=1.0, gt=0, description="frames per second")
    pose_known: bool = Field(
        default=True, description="publish the camera's true pose as a surveyed calibration (pose_trusted)"
    )
    oracle: bool = Field(default=False, description="also publish ORACLE ground truth (ids, depth, true pose)")
    rerender: bool = Field(default=False, description="render every frame instead of once (static world)")

    @model_validator(mode="after")
    def _index(self) -> Config:
        if self.camera_index >= self.n_cameras:
            raise ValueError(f"camera_index {self.camera_index} needs n_cameras > {self.camera_index}")
        return self


class SimCamera(SourceBase):
    def __init__(self, config: Config) -> None:
        self.config = config
        self.rate_hz = config.rate_hz
        self.intrinsics = Intrinsics.from_fov(config.width, config.height, config.hfov_deg)
        self._renderer: Any = None
        self._camera: Any = None
        self._labels: dict[int, str] = {}
        self._cached: Any = None

    def open(self) -> None:
        if self._renderer is not None:
            return  # the scene survives reconnects
        try:
            from sim.cameras import place_fixed_cameras
            from sim.render import Renderer
            from sim.scene import generate_scene
        except ImportError as e:
            raise SourceConfigError(f"the sim source needs the simulator (server extra): {e}") from None
        c = self.config
        scene = generate_scene(c.family, c.seed)
        renderer = Renderer(scene)
        cams = place_fixed_cameras(scene, c.n_cameras, c.seed, self.intrinsics, renderer=renderer)
        self._camera = cams[c.camera_index]
        self._labels = {o.obj_id: o.label for o in scene.objects}
        self._renderer = renderer

    def read(self) -> Grab:
        c = self.config
        if self._cached is None or c.rerender:
            self._cached = self._renderer.render(self.intrinsics, self._camera.T_world_cam)
        out = self._cached
        T = np.asarray(self._camera.T_world_cam, dtype=np.float64)
        oracle = (
            OracleCapture(T_world_cam_true=T, instance_id=out.instance_id, depth_m=out.depth_m, labels=self._labels)
            if c.oracle
            else None
        )
        known = c.pose_known and bool(self._camera.pose_known)
        return Grab(
            rgb=out.rgb,
            stamp_ns=time.time_ns(),
            intrinsics=self.intrinsics,
            T_world_cam=T if known else None,
            pose_trusted=known,
            oracle=oracle,
        )


def create(config: Config) -> SimCamera:
    return SimCamera(config)
