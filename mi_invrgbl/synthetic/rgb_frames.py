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

from ..scene.posing import place
from . import writers


class FramePoser:
    """Moves the dynamic parts of a loaded street scene to a given frame
    (with :func:`mi_invrgbl.scene.posing.place`)."""

    def __init__(self, scene, car_poses: np.ndarray, headlights=()):
        self.scene = scene
        self.params = mi.traverse(scene)
        self.car_poses = np.asarray(car_poses, np.float64)
        # The car and its headlights were loaded at the car's frame-0 pose.
        self.moving = ["moving_car"] + ["headlight_%d" % i for i in range(len(headlights))
                                        if "headlight_%d.to_world" % i in self.params]

    def set_frame(self, frame: int, sensor_to_world: np.ndarray | None = None) -> None:
        poses = {name: self.car_poses[frame] for name in self.moving}
        if sensor_to_world is not None:
            poses["sensor"] = sensor_to_world
        place(self.scene, poses, {name: self.car_poses[0] for name in self.moving}, self.params)


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
