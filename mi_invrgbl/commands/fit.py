"""``mi-invrgbl fit DIR/scene.xml``: two-stage RGB + LiDAR inverse rendering.

See :mod:`mi_invrgbl.fit.runner` for the order of work and
``docs/scene_format.md`` for the input and output files.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from ..errors import UserError

#: Largest loss weight accepted: beyond it the float32 loss overflows.
MAX_WEIGHT = 1e6


#: The fit's options: (flag, FitConfig field, help, argparse options). Types
#: and defaults come from :class:`~mi_invrgbl.fit.config.FitConfig`, the one
#: source of defaults; ``invert`` marks a switch that turns a default-on
#: field off.
FLAGS = (
    ("--output", "output", "output folder (default: <scene folder>/fit); new, empty, or an "
     "earlier fit's (with --resume or --overwrite)", {"short": "-o"}),
    ("--stage1", "stage1_iterations", "stage-1 (geometry) iterations", {}),
    ("--stage2", "stage2_iterations", "stage-2 (materials) iterations", {}),
    ("--width", "fit_width", "image width the fit works at", {}),
    ("--lidar-columns", "lidar_columns", "LiDAR azimuth columns used per scan", {}),
    ("--batch", "batch_rays", "stage-1 camera rays per batch", {}),
    ("--lidar-batch", "lidar_batch_rays", "stage-1 LiDAR beams per batch", {}),
    ("--range-weight", "stage1_range",
     "weight of stage 1's LiDAR range term (L1 in metres; 0: the LiDAR's ranges do not pull "
     "the geometry)", {}),
    ("--samples", "samples", "sky samples M per Gaussian while fitting", {}),
    ("--sky-patterns", "sky_patterns",
     "stage 2 turns the sky directions to one of this many patterns each step, so the albedo "
     "fits the sky integral, not one set of M directions (1: one fixed set)", {}),
    ("--pixel-grid", "pixel_grid",
     "stage 2 averages each camera pixel over N x N rays, as the camera and eval's box filter "
     "integrate a pixel (1: one ray through its centre)", {}),
    ("--bounces", "bounces",
     "diffuse bounces of light between Gaussians in the shading (0: direct sun and sky "
     "light only, as in the paper)", {}),
    ("--shadowing", "shadowing",
     "shadowing-masking term of the specular lobe: Smith's GGX term, or the paper's V-cavity "
     "(about twice the specular near grazing angles)", {"choices": ("smith", "vcavity")}),
    ("--diffuse-fresnel", "diffuse_fresnel",
     "weight the diffuse term by a rough dielectric coat's transmittance on the way in and "
     "out (GGX, the Gaussian's roughness), as Mitsuba's roughplastic does (default: the "
     "paper's plain Lambertian term)", {}),
    ("--rgb-space", "rgb_space",
     "colour space of the camera loss in both stages: sRGB (what PSNR and the eye compare) or "
     "linear (the paper's)", {"choices": ("srgb", "linear")}),
    ("--rgb-norm", "rgb_norm",
     "norm of the camera loss in both stages: the absolute difference (l1) or the paper's "
     "squared difference (l2)", {"choices": ("l1", "l2")}),
    ("--render-samples", "render_samples",
     "sky samples M written into the fitted scene.xml: 'auto' (the smallest of 4/8/16/32, "
     "up to --samples, within 0.1 dB of the best validation PSNR) or a number", {}),
    ("--weights", "weights",
     "loss weights, e.g. 'rgb2lidar=0,lidar2rgb=0' (paper defaults: lidar=rgb=1, nor=mat=0.1, "
     "rgb2lidar=lidar2rgb=0.05; plus anchor=1, stage 2's pull of the normals back to their "
     "start; 0 switches a term off)", {"text": True}),
    ("--sigma", "bilateral_sigma", "bilateral sigma of L_rgb->lidar", {}),
    ("--sun", "sun", "use a sun: decided from the data (auto) or forced",
     {"choices": ("auto", "on", "off")}),
    ("--sun-trial", "sun_trial_iterations",
     "stage-2 iterations with and without a sun the sun test rejected narrowly; the lighting "
     "scoring higher on the validation frames is kept (0: the test decides alone)", {}),
    ("--sh-order", "sh_order", "SH order of the sky: decided from the visible sky (auto) or forced",
     {"choices": ("auto", "0", "1", "2", "3")}),
    ("--lidar-model", "lidar_model",
     "LiDAR reflectance: keep the specular lobe only if it lowers validation error (auto)",
     {"choices": ("auto", "pbr", "lambertian")}),
    ("--no-response", "fit_response",
     "keep the paper's cos/d^2 LiDAR response instead of estimating it", {"invert": True}),
    ("--per-frame-visibility", "per_frame_visibility",
     "trace sky/sun visibility per frame so moving objects' shadows move (G x M shadow rays "
     "per frame; default: once, objects placed as in the first training frame)", {}),
    ("--sun-visibility", "sun_visibility",
     "per-Gaussian sun visibility: traced at stage 2's start and then learned (the paper's "
     "v_sun; shadows of occluders the fit lacks), or traced only",
     {"choices": ("learn", "trace")}),
    ("--learn-sun-direction", "learn_sun_direction",
     "also refine the selected sun direction in stage 2 (with learned sun visibility; it moves "
     "only the n.l shading, so albedo can absorb it)", {}),
    ("--sharpen-sun", "sharpen_sun",
     "sharpen the direction of a sun the lighting selection uses or tries: 400 directions "
     "scanned through 4000 of the Gaussians, the 4 best peaks refined through all (the true "
     "sun's peak is a few degrees wide; costs about 1-2 minutes on 2 cores, not yet planned "
     "by --budget)", {}),
    ("--no-sky-mask", "sky_mask",
     "do not mark the images' sky for stage 1 (default: bright, smooth pixels connected to the top "
     "edge, with no LiDAR return or moving object there, are fitted as sky, not Gaussians; switch "
     "it off for scenes without sky, e.g. indoors under a white ceiling above the LiDAR's top beam)",
     {"invert": True}),
    ("--fixed-object-poses", "object_poses",
     "keep the moving objects' poses as imported (default: stage 1 corrects each object's pose "
     "at every training frame from the images and LiDAR; other frames interpolate)",
     {"invert": True}),
    ("--free-object-extent", "object_bounds",
     "let a labelled moving object's Gaussians grow past the box of its imported centres "
     "(default: stage 1 keeps them inside it, so an object cannot draw its own shadow on the "
     "road; objects the import found by LiDAR motion are never held)",
     {"invert": True}),
    ("--static-object-shadows", "moving_shadows",
     "leave the moving objects' sun shadows to the learned, static sun visibility (default: "
     "stage 2 and the fitted scene trace the sun through the moving objects in every frame, so "
     "their shadows move with them)", {"invert": True}),
    ("--keep-sky-lookalikes", "prune_sky_lookalikes",
     "keep stage-1 Gaussians that have the sky's colour and only sky behind them (default: "
     "removed before stage 2; they cast shadows no roof casts)", {"invert": True}),
    ("--validation-every", "validation_every",
     "every N-th training frame is a validation frame (index %% N == min(2, N // 2)): not "
     "trained on, it scores the model choices and the early stop (0: none; selection then "
     "scores training frames)", {}),
    ("--budget", "budget_minutes",
     "wall-time budget in minutes: both stages' iterations, stage 1's batch and learning-rate "
     "schedule from the measured speed, early stop on validation frames (overrides "
     "--stage1/--stage2; 0: none)", {}),
    ("--max-gaussians", "max_gaussians", "densification cap", {}),
    ("--densify-fraction", "densify_fraction",
     "share of the Gaussians stage 1 splits at each densification (those with the largest "
     "positional gradients)", {}),
    ("--densify-screen", "densify_screen",
     "rank the Gaussians to split by their positional gradient in image space (the gradient "
     "in metres times the distance from the camera) instead of in metres", {}),
    ("--densify-scope", "densify_scope",
     "rank the Gaussians to split within each node (a moving object grows by the same share as "
     "the background) or over the whole scene", {"choices": ("node", "scene")}),
    ("--checkpoint-every", "checkpoint_every", "iterations between checkpoints", {}),
    ("--eval-every", "eval_every", "iterations between held-out evaluations", {}),
    ("--resume", "resume", "continue the fit in the output folder from its "
     "checkpoints/latest.npz", {}),
    ("--seed", "seed", "random seed", {}),
)


def _defaults():
    import dataclasses
    from ..fit.config import FitConfig
    return {f.name: getattr(FitConfig(), f.name) for f in dataclasses.fields(FitConfig)}


def add_parser(sub):
    p = sub.add_parser("fit", help="fit geometry, materials, light and LiDAR response to an imported scene")
    p.add_argument("scene", help="scene.xml written by 'mi-invrgbl import'")
    defaults = _defaults()
    for flag, name, text, opts in FLAGS:
        opts = dict(opts)
        names = [opts.pop("short")] if "short" in opts else []
        names.append(flag)
        default = defaults[name]
        metavar = flag.lstrip("-").upper().replace("-", "_")
        if opts.pop("invert", False):
            p.add_argument(*names, dest=name, action="store_false", default=default, help=text)
        elif isinstance(default, bool):
            p.add_argument(*names, dest=name, action="store_true", default=default, help=text)
        elif opts.pop("text", False):
            p.add_argument(*names, dest=name, default="", metavar=metavar, help=text)
        else:
            shown = "" if name == "output" else " (default: %(default)s)"
            if "choices" not in opts:
                opts["metavar"] = metavar
            p.add_argument(*names, dest=name, type=type(default), default=default,
                           help=text + shown, **opts)
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier fit in the output folder (only the files it wrote)")
    p.set_defaults(run=run)


def config_from_args(args):
    from ..fit.losses import LossWeights
    from ..fit.config import FitConfig
    values = {name: getattr(args, name) for _, name, _, _ in FLAGS}
    try:
        values["weights"] = LossWeights.parse(values["weights"])
    except ValueError as exc:
        raise UserError("--weights: %s" % exc) from None
    for name, value in values["weights"].as_dict().items():
        if not value <= MAX_WEIGHT:
            raise UserError("--weights: %s=%g is too large (at most %g: the float32 loss "
                            "would overflow)" % (name, value, MAX_WEIGHT))
    if args.resume and getattr(args, "overwrite", False):
        raise UserError("--resume and --overwrite exclude each other")
    for flag, name, _, _ in FLAGS:
        if name in ("stage1_iterations", "stage2_iterations", "fit_width", "lidar_columns",
                    "batch_rays", "lidar_batch_rays", "samples", "sky_patterns", "pixel_grid"):
            if values[name] < (0 if name.startswith("stage") else 1):
                raise UserError("%s must be positive" % flag)
    from ..fit.config import MAX_PIXEL_GRID
    if values["pixel_grid"] > MAX_PIXEL_GRID:
        raise UserError("--pixel-grid must be in 1..%d (got %r)" % (MAX_PIXEL_GRID, values["pixel_grid"]))
    from ..physics.lighting import MAX_BOUNCES
    if not 0 <= values["bounces"] <= MAX_BOUNCES:
        raise UserError("--bounces must be in 0..%d (got %r)" % (MAX_BOUNCES, values["bounces"]))
    if not values["budget_minutes"] >= 0:
        raise UserError("--budget must be a number of minutes >= 0 (got %r)"
                        % values["budget_minutes"])
    if not 0 <= values["stage1_range"] <= MAX_WEIGHT:
        raise UserError("--range-weight must be in 0..%g (got %r)" % (MAX_WEIGHT, values["stage1_range"]))
    if not 0 <= values["densify_fraction"] <= 1:     # (also refuses nan)
        raise UserError("--densify-fraction must be in 0..1 (got %r)" % values["densify_fraction"])
    render_samples = str(values["render_samples"]).strip().lower()
    if render_samples != "auto" and not (render_samples.isdigit() and int(render_samples) >= 1):
        raise UserError("--render-samples must be 'auto' or a positive number (got %r)"
                        % values["render_samples"])
    values["render_samples"] = render_samples
    return FitConfig(**values)


def output_folder(args) -> str:
    """The fit's output folder: ``-o`` or ``fit/`` beside the scene."""
    return args.output or os.path.join(os.path.dirname(os.path.abspath(args.scene)), "fit")


def _carry_frames(scene, staging: Path, target: Path) -> None:
    """A fit folder outside its import folder gets a copy of ``frames.json``
    (paths rewritten relative to it), so that ``eval`` finds the frames and
    their observations from the fit folder alone."""
    from ..scene.frames import Frames
    if (target.parent / "frames.json").is_file():
        return
    try:
        frames = Frames.load(scene)
    except UserError:
        return
    if frames.root != target.parent:
        frames.save(staging / "frames.json")


def run(args):
    from .. import outdir
    from ..fit.runner import run_fit
    config = config_from_args(args)
    if not os.path.isfile(args.scene):
        raise UserError("%s: scene file not found" % args.scene)
    # Decided before any work: a fit must not run an hour and then fail to write.
    out = outdir.prepare(output_folder(args), "fit", inputs=[args.scene],
                         overwrite=args.overwrite, resume=args.resume)
    if args.resume and not (out.path / "checkpoints" / "latest.npz").is_file():
        out.discard()
        raise UserError("%s: no checkpoint to resume from"
                        % (out.target / "checkpoints" / "latest.npz"))
    config.output = str(out.path)
    t0 = time.time()
    try:
        # Before the fit: its outputs step loads the fitted scene with its frames.
        _carry_frames(args.scene, out.path, out.target)
        metrics = run_fit(args.scene, config, log=out.log)
    except UserError as exc:
        out.discard()
        # Name the output folder, not the temporary one the fit worked in.
        raise UserError(str(exc).replace(str(out.path), str(out.target))) from None
    except BaseException:
        out.discard()
        raise
    out.commit(complete=not metrics["interrupted"])
    print("[fit] %s in %.0f s; held-out PSNR %s dB, LiDAR intensity RMSE %s; peak memory %.0f MB"
          % ("interrupted" if metrics["interrupted"] else "done", time.time() - t0,
             "%.2f" % metrics["heldout_psnr"] if metrics["heldout_psnr"] is not None else "n/a",
             "%.4f" % metrics["heldout_intensity_rmse"] if metrics["heldout_intensity_rmse"] is not None
             else "n/a", metrics["peak_rss_mb"]))
    print("[fit] results in %s%s" % (out.target, "" if not metrics["interrupted"] else
                                     " (continue with --resume)"))
    return 130 if metrics["interrupted"] else 0
