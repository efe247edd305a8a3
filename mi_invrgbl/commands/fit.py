"""``mi-invrgbl fit DIR/scene.xml``: two-stage RGB + LiDAR inverse rendering.

See :mod:`mi_invrgbl.fit.runner` for the order of work and
``docs/scene_format.md`` for the input and output files.
"""

from __future__ import annotations

import time

from ..errors import UserError


def add_parser(sub):
    p = sub.add_parser("fit", help="fit geometry, materials, light and LiDAR response to an imported scene")
    p.add_argument("scene", help="scene.xml written by 'mi-invrgbl import'")
    p.add_argument("-o", "--output", default="", help="output folder (default: <scene folder>/fit)")
    p.add_argument("--stage1", type=int, default=150, help="stage-1 (geometry) iterations (default 150)")
    p.add_argument("--stage2", type=int, default=200, help="stage-2 (materials) iterations (default 200)")
    p.add_argument("--width", type=int, default=320, help="image width the fit works at (default 320)")
    p.add_argument("--lidar-columns", type=int, default=512,
                   help="LiDAR azimuth columns used per scan (default 512)")
    p.add_argument("--batch", type=int, default=4096, help="stage-1 rays per batch (camera and LiDAR each)")
    p.add_argument("--samples", type=int, default=16, help="sky samples M per Gaussian while fitting (default 16)")
    p.add_argument("--render-samples", default="auto",
                   help="sky samples M written into the fitted scene.xml: 'auto' (the smallest of "
                        "4/8/16/32 within 0.1 dB of the best validation PSNR) or a number")
    p.add_argument("--weights", default="",
                   help="loss weights, e.g. 'rgb2lidar=0,lidar2rgb=0' (paper defaults: lidar=rgb=1, "
                        "nor=mat=0.1, rgb2lidar=lidar2rgb=0.05; 0 switches a term off)")
    p.add_argument("--sigma", type=float, default=0.1, help="bilateral sigma of L_rgb->lidar")
    p.add_argument("--sun", choices=("auto", "on", "off"), default="auto",
                   help="use a sun: decided from the data (auto) or forced")
    p.add_argument("--sh-order", choices=("auto", "0", "1", "2", "3"), default="auto",
                   help="SH order of the sky: decided from the visible sky (auto) or forced")
    p.add_argument("--lidar-model", choices=("auto", "pbr", "lambertian"), default="auto",
                   help="LiDAR reflectance: keep the specular lobe only if it lowers validation error (auto)")
    p.add_argument("--no-response", action="store_true",
                   help="keep the paper's cos/d^2 LiDAR response instead of estimating it")
    p.add_argument("--per-frame-visibility", action="store_true",
                   help="trace sky/sun visibility per frame so moving objects' shadows move "
                        "(G x M shadow rays per frame; default: once, objects at their first pose)")
    p.add_argument("--sun-visibility", choices=("learn", "trace"), default="learn",
                   help="per-Gaussian sun visibility: traced at stage 2's start and then learned "
                        "(the paper's v_sun; shadows of occluders the fit lacks), or traced only")
    p.add_argument("--learn-sun-direction", action="store_true",
                   help="also refine the selected sun direction in stage 2 (with learned sun "
                        "visibility; it moves only the n.l shading, so albedo can absorb it)")
    p.add_argument("--keep-sky-lookalikes", action="store_true",
                   help="keep stage-1 Gaussians that have the sky's colour and only sky behind "
                        "them (default: removed before stage 2; they cast shadows no roof casts)")
    p.add_argument("--budget", type=float, default=0.0, metavar="MINUTES",
                   help="wall-time budget: both stages' iterations, stage 1's batch and learning-rate "
                        "schedule from the measured speed, early stop on validation frames "
                        "(overrides --stage1/--stage2)")
    p.add_argument("--max-gaussians", type=int, default=800000, help="densification cap")
    p.add_argument("--checkpoint-every", type=int, default=50)
    p.add_argument("--eval-every", type=int, default=50)
    p.add_argument("--resume", action="store_true", help="continue from DIR/fit/checkpoints/latest.npz")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(run=run)


def config_from_args(args):
    from ..fit.losses import LossWeights
    from ..fit.runner import FitConfig
    try:
        weights = LossWeights.parse(args.weights)
    except ValueError as exc:
        raise UserError("--weights: %s" % exc) from None
    for name in ("stage1", "stage2", "width", "lidar_columns", "batch", "samples"):
        if getattr(args, name) < (0 if name.startswith("stage") else 1):
            raise UserError("--%s must be positive" % name.replace("_", "-"))
    if not args.budget >= 0:
        raise UserError("--budget must be a number of minutes >= 0 (got %r)" % args.budget)
    render_samples = str(args.render_samples).strip().lower()
    if render_samples != "auto" and not (render_samples.isdigit() and int(render_samples) >= 1):
        raise UserError("--render-samples must be 'auto' or a positive number (got %r)"
                        % args.render_samples)
    return FitConfig(output=args.output, stage1_iterations=args.stage1, stage2_iterations=args.stage2,
                     fit_width=args.width, lidar_columns=args.lidar_columns, batch_rays=args.batch,
                     samples=args.samples, render_samples=render_samples, weights=weights,
                     bilateral_sigma=args.sigma, sun=args.sun,
                     sh_order=args.sh_order, lidar_model=args.lidar_model,
                     fit_response=not args.no_response, max_gaussians=args.max_gaussians,
                     checkpoint_every=args.checkpoint_every, eval_every=args.eval_every,
                     resume=args.resume, seed=args.seed,
                     per_frame_visibility=args.per_frame_visibility,
                     sun_visibility=args.sun_visibility,
                     prune_sky_lookalikes=not args.keep_sky_lookalikes,
                     learn_sun_direction=args.learn_sun_direction,
                     budget_minutes=args.budget)


def run(args):
    from ..fit.runner import run_fit
    t0 = time.time()
    metrics = run_fit(args.scene, config_from_args(args))
    print("[fit] %s in %.0f s; held-out PSNR %s dB, LiDAR intensity RMSE %s; peak memory %.0f MB"
          % ("interrupted" if metrics["interrupted"] else "done", time.time() - t0,
             "%.2f" % metrics["heldout_psnr"] if metrics["heldout_psnr"] is not None else "n/a",
             "%.4f" % metrics["heldout_intensity_rmse"] if metrics["heldout_intensity_rmse"] is not None
             else "n/a", metrics["peak_rss_mb"]))
    return 130 if metrics["interrupted"] else 0
