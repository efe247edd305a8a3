"""The fit's options (``mi-invrgbl fit`` flags map onto these fields)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from .losses import LossWeights
from .budget import ANNEAL_END, ANNEAL_FROM

#: Fields that change the fitted model (a checkpoint written with other values
#: cannot be resumed). Iteration counts, logging, output and the options that
#: only force a selection (whose outcome the checkpoint records) are not among them.
MODEL_FIELDS = ("batch_rays", "lidar_batch_rays", "fit_width", "lidar_columns", "max_hits", "min_transmittance",
                "samples", "sky_patterns", "pixel_grid", "bounces", "shadowing", "diffuse_fresnel", "rgb_space", "rgb_norm", "weights", "bilateral_sigma", "slic_size", "lr_scale", "densify_every",
                "densify_until", "anneal_from", "anneal_end", "prune_opacity", "densify_grad",
                "densify_fraction", "densify_screen", "densify_scope", "split_scale",
                "max_gaussians", "stage1_range", "stage1_drop", "stage1_sky", "seed", "fit_response",
                "sun_candidates", "sun_gaussians", "per_frame_visibility", "learn_sun_direction",
                "sharpen_sun", "prune_sky_lookalikes", "sky_mask", "sun_visibility", "validation_every",
                "object_poses", "object_bounds", "moving_shadows")


#: Largest ``pixel_grid`` (rays per pixel side in stage 2's camera hits).
MAX_PIXEL_GRID = 4


@dataclass
class FitConfig:
    output: str = ""
    stage1_iterations: int = 150
    stage2_iterations: int = 200
    batch_rays: int = 4096
    #: Stage 1's LiDAR beams per step. The Gaussians start on the LiDAR
    #: points, so the beams only keep the geometry from drifting; each costs
    #: about what a camera ray does, and the camera rays are what a fit on a
    #: CPU is short of (docs/measurements.md, "Half the LiDAR beams per
    #: stage-1 step").
    lidar_batch_rays: int = 1024
    fit_width: int = 320
    lidar_columns: int = 512
    #: Most Gaussians blended per ray, in the fit and in the fitted scenes.
    #: Stage 1 on the KITTI excerpt (600 steps, validation frames,
    #: ``tests/bench/stage1_steps.py --set max_hits=K``): 16.49 / 19.14 /
    #: 19.49 / 19.40 dB at K = 16 / 24 / 32 / 48, for 201 / 216 / 224 / 223 s
    #: of steps: rays cut off early fill the rest of their weight with sky,
    #: and the cut costs far more than the few extra hits.
    max_hits: int = 32
    min_transmittance: float = 1e-2
    samples: int = 16
    render_samples: str = "auto"  # auto | N: sky samples M written into scene.xml
    #: Diffuse bounces between Gaussians in stage 2's shading and in the
    #: fitted scene's integrator (:mod:`..physics.lighting`); 0: direct light only.
    bounces: int = 1
    #: Shadowing-masking term of the Gaussians' specular lobe in stage 2 and
    #: in the fitted scene's integrator: "smith" or "vcavity" (the paper's).
    #: Towards grazing the V-cavity lobe reflects about twice as much sky,
    #: which a facade seen along a street in shadow can only answer with
    #: near-zero albedo. On two synthetic streets (fixed 300/300 iterations,
    #: one run each) Smith scored 0.73 and 0.09 dB higher on the validation
    #: frames and cut the roughness error from 0.32 to 0.27 and 0.31 to 0.27.
    shadowing: str = "smith"
    #: Diffuse light through a rough dielectric coat (``invrgbl``'s
    #: ``diffuse_fresnel``, :mod:`mi_invrgbl.physics.coat`): the Lambertian
    #: term weighted by the coat's transmittance at the light's and the
    #: viewer's angle (GGX alpha = the Gaussian's roughness) and by the light
    #: that bounces under the coat, as Mitsuba's ``roughplastic`` weights its
    #: diffuse lobe. Off: the paper's Lambertian term. A rough coat keeps far
    #: less than a smooth one: at alpha 0.8-0.9 (the street's road, sidewalk
    #: and wall) the coated lobe is 0.41-0.44 of a Lambertian one lit and seen
    #: head-on and 0.21-0.25 seen 80 degrees from the normal, where a car's
    #: camera sees the ground (docs/measurements.md, "Where the albedo error sits").
    diffuse_fresnel: bool = False
    #: Colour space the camera loss compares in (``losses.RGB_SPACES``).
    #: sRGB weighs an error as the 8-bit image and PSNR do, so dark pixels
    #: (shadow, foliage) count for more than in linear light. Stage 1 on the
    #: KITTI excerpt (600 steps, validation frames,
    #: ``tests/bench/stage1_steps.py --set rgb_space=...``): 20.65 dB in sRGB
    #: against 19.49 in linear light (19.24 against 17.76 at 200 steps).
    rgb_space: str = "srgb"
    #: Norm of the camera loss in both stages (``losses.RGB_NORMS``): the
    #: absolute difference, or the paper's squared difference. 30-minute
    #: KITTI fit, ``eval``: 22.22 dB, SSIM 0.791 with l1 against 21.79-21.99
    #: and 0.742-0.754 with l2; the street's 8-minute main job 29.27 dB,
    #: relighting 23.66 against 28.45 and 23.37, its normals 16.0 degrees
    #: against 13.5 (docs/measurements.md, "The camera loss as an
    #: absolute difference").
    rgb_norm: str = "l1"
    #: Stage 2 turns each Gaussian's M sky directions to another of this many
    #: patterns every step (each pattern's visibility is traced once), so the
    #: albedo fits the sky integral rather than one fixed set of directions.
    #: Off by default: on the street 4 patterns cut the loss from rendering
    #: with 32 directions from 1.3 to 0.2-0.6 dB but moved neither albedo nor
    #: relighting, and tracing them took 2 GB and, at an 8-minute budget, a
    #: third of stage 2's steps (KITTI, with them: freezing 210 s, 5 steps left).
    sky_patterns: int = 1
    #: Stage 2 integrates each camera pixel over a ``pixel_grid`` x
    #: ``pixel_grid`` set of rays (:func:`.render.freeze_pixels`), as the
    #: camera and ``eval``'s box filter do; 1: one ray through the centre.
    #: Off by default: at 2 x 2, KITTI at 30 minutes scored 21.99 and
    #: 21.75 dB in two runs (21.76-21.90 in four at 1 x 1); the first run's
    #: stage 1 had ended 0.1-0.2 dB higher on the validation frames than
    #: the others, the second's 0.2 dB lower (21.83), and eval less
    #: stage 1's validation score was -0.23 and -0.08 dB (-0.17 to -0.28 at 1 x 1);
    #: the street at 8 minutes kept its PSNR (28.54 against 28.53) while
    #: freezing took 65 s instead of 41, stage 2 ran 92 steps instead of
    #: 248 and the albedo RMSE rose from 0.173 to 0.207.
    pixel_grid: int = 1
    weights: LossWeights = field(default_factory=LossWeights)
    bilateral_sigma: float = 0.1
    slic_size: int = 12
    lr_scale: float = 1.0
    densify_every: int = 50
    densify_until: float = 0.7
    #: A budgeted stage 1's learning rates other than the positions' keep
    #: their start up to this fraction of the stage, then fall exponentially
    #: to ``anneal_end`` of it at the end (:func:`.budget.anneal_lr_factor`).
    anneal_from: float = ANNEAL_FROM
    anneal_end: float = ANNEAL_END
    prune_opacity: float = 0.02
    densify_grad: float = 1e-7
    densify_fraction: float = 0.02
    #: Rank Gaussians for densification by their positional gradient times
    #: their distance from the step's camera (about the gradient in image
    #: space, as 3D Gaussian Splatting ranks them) instead of the gradient in
    #: metres, which favours the Gaussians nearest the cameras.
    densify_screen: bool = False
    #: Where the densification's quota is ranked: ``node``, the top
    #: ``densify_fraction`` of each node's Gaussians (every moving object
    #: grows as fast as the background, however few pixels it covers), or
    #: ``scene``, the top fraction of all Gaussians ranked together, so the
    #: splits go where the gradients are largest.
    densify_scope: str = "node"
    #: Densification splits a growing Gaussian larger than this (metres,
    #: largest axis) in two and clones a smaller one. 0: every growing
    #: Gaussian is split. Clones hurt on the street: with the split size at
    #: 0.3 m (most growing Gaussians cloned) stage 1's held-out PSNR fell from
    #: 24.6 dB at step 150 to 23.4 at 300, splitting them all kept it rising
    #: to 25.5 dB at 400 (as without densification); on the KITTI excerpt the
    #: two were alike at 300 steps.
    split_scale: float = 0.0
    max_gaussians: int = 800000
    #: Weight of stage 1's LiDAR range term (L1 in metres). On the KITTI
    #: excerpt the range term held the camera's fit back: after 600 stage-1
    #: steps the validation PSNR was 18.46 dB at weight 1, 18.98 at 0.3 and
    #: 19.25 at 0.1; camera rays alone reached 18.19 at 200 steps and fell
    #: to 18.04 at 400 (``tests/bench/stage1_steps.py --set stage1_range=W``).
    stage1_range: float = 0.1
    stage1_drop: float = 0.1
    #: Weight of stage 1's sky term: the blended opacity pushed to 0 (BCE)
    #: on the pixels the sky mask (:mod:`.sky_mask`) marks; 0: no mask.
    stage1_sky: float = 0.1
    eval_every: int = 50
    #: Stage 1 scores its progress (held-out log, validation early stop) on
    #: every n-th pixel that counts (:func:`.evaluate.score_stage1`).
    score_stride: int = 4
    checkpoint_every: int = 50
    seed: int = 0
    resume: bool = False
    sun: str = "auto"            # auto | on | off
    #: With ``sun="auto"``: where the sun test rejected a sun by a small
    #: margin (:data:`.model_selection.SUN_TRIAL_GAIN`), stage 2 runs this
    #: many iterations with and without it and keeps the lighting that
    #: scores higher on the validation frames (0: the test decides alone).
    sun_trial_iterations: int = 100
    sh_order: str = "auto"       # auto | 0..3
    lidar_model: str = "auto"    # auto | pbr | lambertian
    fit_response: bool = True
    lobe_iterations: int = 60
    sun_candidates: int = 48
    sun_gaussians: int = 20000
    #: Trace the sky and sun visibility with the objects where each frame has
    #: them. Off by default: once, placed as in the first training frame.
    #: On the KITTI excerpt one trace of its 137 000 Gaussians took 54-61 s
    #: on 2 cores, 40 frames about 40 minutes, while the one placement cost
    #: ``eval`` 0.11-0.17 dB on held-out frames (docs/measurements.md, "Where
    #: the moving objects are lit").
    per_frame_visibility: bool = False
    learn_sun_direction: bool = False  # stage 2 refines the selected sun direction (opt-in)
    #: Sharpen the direction of a sun the lighting selection uses or tries
    #: (:func:`.selection.sharpen_sun`): on one stage 1 of the street it took
    #: the sun from 12-32 degrees off to 1 degree, on another a false peak
    #: scored as high as the true one; it costs 60-110 s on 2 cores that the
    #: budget does not plan for yet (the main job ran 527 s of its 8
    #: minutes), so it is opt-in (docs/measurements.md, "The sun's search: a
    #: narrow peak among broad ones").
    sharpen_sun: bool = False
    prune_sky_lookalikes: bool = True  # drop sky-coloured Gaussians with only sky behind them
    sky_mask: bool = True  # mark the images' sky for stage 1 (.sky_mask); weight: stage1_sky
    sun_visibility: str = "learn"  # learn | trace: the paper's per-Gaussian v_sun, or traced only
    #: Stage 1 corrects the moving objects' per-frame poses (.object_poses).
    object_poses: bool = True
    #: Stage 1 keeps each labelled moving object's Gaussians inside the box
    #: of its imported centres (.object_bounds): it cannot paint its shadow.
    object_bounds: bool = True
    #: With a learned sun visibility (the static scene's shadows), stage 2
    #: and the fitted scene's integrator multiply it, per frame, by the
    #: sun's transmittance through the moving objects where the frame has
    #: them (``physics.lighting.moving_shadows``): their shadows move.
    moving_shadows: bool = True
    #: Every n-th training frame (``index % n == min(2, n // 2)``, :func:`.init.
    #: split_validation`) is a validation frame:
    #: not trained on, it scores the model selection. 0: no validation split
    #: (selection then scores training frames). Held-out frames never take part.
    validation_every: int = 5
    #: Wall-time budget in minutes (0: none). Sets both stages' iterations,
    #: stage 1's batch size and position learning-rate schedule from the
    #: measured iteration speed, and stops a stage early once its validation
    #: score stops improving (:mod:`.budget`); ``stage*_iterations`` are then unused.
    budget_minutes: float = 0.0

    def to_json(self):
        d = asdict(self)
        d["weights"] = self.weights.as_dict()
        return d

    def model_fields(self) -> dict:
        """The values of :data:`MODEL_FIELDS` (for the resume fingerprint)."""
        d = self.to_json()
        return {k: d[k] for k in MODEL_FIELDS}
