"""RGB rendering of every frame with Mitsuba's stock ``path`` integrator.

A scene file is loaded once; each frame then only moves the sensor, the
moving car and its headlights through ``mi.traverse``. Updating parameters in
place keeps Dr.Jit's compiled kernels valid, so every frame after the first
reuses them (the first frame of each scene pays the compilation).
"""

from __future__ import annotations

import os

import numpy as np
import mitsuba as mi

from . import scene_xml, writers


class FramePoser:
    """Moves the dynamic parts of a loaded street scene to a given frame."""

    def __init__(self, scene, car_poses: np.ndarray, headlights=()):
        self.scene = scene
        self.params = mi.traverse(scene)
        self.car_poses = car_poses
        self.headlights = list(headlights)
        # The car was loaded at its frame-0 pose: recover its local vertices
        # from the loaded ones instead of assuming the PLY's vertex order.
        world0 = np.array(self.params["moving_car.vertex_positions"], dtype=np.float64).reshape(-1, 3)
        inv0 = np.linalg.inv(car_poses[0])
        self.car_local = world0 @ inv0[:3, :3].T + inv0[:3, 3]

    def set_frame(self, frame: int, sensor_to_world: np.ndarray | None = None) -> None:
        pose = self.car_poses[frame]
        world = self.car_local @ pose[:3, :3].T + pose[:3, 3]
        self.params["moving_car.vertex_positions"] = mi.Float(world.astype(np.float32).reshape(-1))
        if sensor_to_world is not None:
            self.params["sensor.to_world"] = mi.Transform4f(mi.ScalarMatrix4f(sensor_to_world))
        for i, light in enumerate(self.headlights):
            key = "headlight_%d.to_world" % i
            if key in self.params:
                m = scene_xml.headlight_to_world(pose, light)
                self.params[key] = mi.Transform4f(mi.ScalarMatrix4f(m))
        self.params.update()


def render_sequence(xml_path: str, out_dir: str, sensor_poses: np.ndarray,
                    car_poses: np.ndarray, headlights, spp: int, seed: int,
                    png_dir: str | None = None) -> None:
    """Render every frame of one lighting to ``out_dir/NNNNNN.exr`` (linear RGB).

    With ``png_dir`` the frames are also written as 8-bit sRGB PNGs there (the
    KITTI ``image_2`` folder). Each frame has its own sampler seed derived from
    ``seed`` so reruns with the same seed draw the same samples.
    """
    scene = mi.load_file(xml_path)
    poser = FramePoser(scene, car_poses, headlights)
    os.makedirs(out_dir, exist_ok=True)
    for i in range(len(sensor_poses)):
        poser.set_frame(i, sensor_poses[i])
        image = np.array(mi.render(scene, spp=spp, seed=seed * 100003 + i), dtype=np.float32)
        image = image[..., :3]
        writers.write_exr(os.path.join(out_dir, "%06d.exr" % i), image)
        if png_dir is not None:
            writers.write_png_srgb(os.path.join(png_dir, "%06d.png" % i), image)
