"""What the fit's steps share: one declared dataclass, built by :func:`.init.load_state`.

Every field is declared here; no step adds attributes from outside. Steps
that choose something (:mod:`.model_selection`) read this state and return
their choice; the recipe in :mod:`.runner` applies it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import mitsuba as mi

from ..scene.frames import Frames
from .config import FitConfig
from .model import GaussianModel
from .observations import FrameObservation
from .progress import SpeedErrorLog
from .render import Response
from ..physics.host_arrays import jit_array


@dataclass
class SkyKeys:
    """The scene's ``shsun`` emitter and its ``mi.traverse`` keys."""
    emitter: object
    sh: str
    sun_irradiance: str
    sun_direction: str


@dataclass
class Stage2Start:
    """What a stage-2 run changes in :class:`FitState` besides the scene's
    lighting: enough to run a second candidate from the same start and go
    back to the first (:func:`mi_invrgbl.fit.runner.sun_trial`)."""
    values: dict              #: node name -> its values (arrays are replaced, never written into)
    lr_state: dict
    shading_init: object
    sun_visibility_learned: bool
    moving_shadows: bool


@dataclass
class FitState:
    scene_path: str
    config: FitConfig
    log: Callable
    rng: np.random.Generator
    frames: Frames
    scene: mi.Scene
    params: mi.SceneParameters
    model: GaussianModel
    camera_integrator: object
    lidar_integrator: object
    sky: SkyKeys
    observations: list
    #: Frames the optimiser steps on.
    train_frames: list
    #: Training frames kept out of the gradient steps to score model selection.
    validation_frames: list
    #: Frames only ``eval`` scores (and the progress log reports); never selection.
    held_out_frames: list
    #: 95th percentile of the observed training intensities (L_lidar's normaliser).
    intensity_scale: float
    response: Response
    speed_log: SpeedErrorLog | None = None
    use_sun: bool = True
    #: SH order of the fitted sky; coefficients above it are held at zero by ``sh_mask``.
    sh_order: int | None = None
    sh_mask: mi.Float | None = None
    sun_visibility_learned: bool = False
    #: Stage 2 multiplies the learned sun visibility by the moving objects'
    #: shadows per frame (``Stage2.moving_shadows``); the fitted scene's
    #: integrator then does too.
    moving_shadows: bool = False
    #: Stage 1's per-frame corrections of the moving objects' poses (None: off or nothing moves).
    object_poses: object = None
    #: The moving objects' boxes stage 1 keeps their Gaussians in
    #: (:class:`.object_bounds.ObjectBox`; empty: off or nothing moves).
    object_boxes: list = field(default_factory=list)
    selection: dict = field(default_factory=dict)
    times: dict = field(default_factory=dict)
    iterations: dict = field(default_factory=dict)   # stage -> last iteration run
    lr_state: dict = field(default_factory=dict)
    t_start: float = 0.0
    #: Wall time of the run a resumed fit continues.
    wall_offset: float = 0.0
    _image_cache: dict = field(default_factory=dict, repr=False)
    _prior_cache: dict = field(default_factory=dict, repr=False)

    # The sky's keys under the names the stages use.
    @property
    def sky_key(self):
        return self.sky.sh

    @property
    def sun_key(self):
        return self.sky.sun_irradiance

    @property
    def sun_dir_key(self):
        return self.sky.sun_direction

    @property
    def sky_emitter(self):
        return self.sky.emitter

    @property
    def fit_dir(self):
        return self.config.output or os.path.join(os.path.dirname(self.scene_path), "fit")

    def stage2_start(self) -> Stage2Start:
        """The point to come back to with :meth:`restore_stage2_start`."""
        return Stage2Start({name: dict(node.values) for name, node in self.model.nodes.items()},
                           dict(self.lr_state), self.selection.get("shading_init"),
                           self.sun_visibility_learned, self.moving_shadows)

    def restore_stage2_start(self, point: Stage2Start) -> None:
        for name, values in point.values.items():
            self.model.nodes[name].values = dict(values)
        self.lr_state.clear()
        self.lr_state.update(point.lr_state)
        self.selection["shading_init"] = point.shading_init
        self.sun_visibility_learned = point.sun_visibility_learned
        self.moving_shadows = point.moving_shadows

    @property
    def selection_frames(self) -> list:
        """Frames that score a model choice: the validation split, else the
        training frames. Never the held-out frames."""
        return self.validation_frames or self.train_frames

    def image_array(self, frame: FrameObservation):
        if frame.index not in self._image_cache:
            img = frame.camera.image.reshape(-1, 3)
            self._image_cache[frame.index] = mi.Color3f(*[jit_array(mi.Float, img[:, c]) for c in range(3)])
        return self._image_cache[frame.index]

    def prior_array(self, frame: FrameObservation, kind):
        key = (frame.index, kind)
        if key not in self._prior_cache:
            p = frame.camera.priors[kind].reshape(frame.camera.width * frame.camera.height, -1)
            if p.shape[1] >= 3:
                self._prior_cache[key] = mi.Vector3f(*[jit_array(mi.Float, p[:, c]) for c in range(3)])
            else:
                self._prior_cache[key] = jit_array(mi.Float, p[:, 0])
        return self._prior_cache[key]
