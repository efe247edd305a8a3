"""Where stage 2's start loses to stage 1, pixel by pixel.

    python tests/bench/start_gap.py FIT CHECKPOINT.npz SCENE.xml [FIT OPTIONS...] [--json OUT.json]

``CHECKPOINT.npz`` is a checkpoint of a fit of ``SCENE.xml`` taken at
stage 2's first iteration (``checkpoints/latest.npz`` as ``fit`` writes it
right after the lighting selection, before freezing, in the fit's output
folder while it runs; copy it before stage 2 overwrites it). ``FIT`` is a
finished fit's folder of the same scene: a copy of it in a temporary
folder, with the checkpoint in place of its own, is resumed with the same
options (they must match the checkpoint's), makes stage 2's start as it
would (``Stage2.init_shading``), and stops there. Neither is touched.

Stage 2 starts from albedo = (stage-1 colour - mean specular) / shading, per
Gaussian, so on every cached hit its radiance differs from stage 1's colour
by two residuals: the specular light this view sees less the mean over the
training views that the start subtracted (``specular``), and the diffuse
light less what the start meant it to be (``diffuse``; nonzero where the
albedo clipped into [0.02, 1] and where the render's shading differs from
the start's). The script composites stage 1's colours through the same
hits and sky (``stage 1 through the cache``), then adds each residual
alone, split by whether the Gaussian's albedo clipped, and reports the
validation PSNR of each, against the start's own render and stage 1's traced
render. The gap a residual closes when left out is its share of the start's
loss.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import json
import os
import shutil
import tempfile

import numpy as np


class Recorded(Exception):
    """Ends the fit once the start is analysed."""


def composite(ray, weight, per_hit, t_after, sky, n_rays):
    """Front-to-back blend of per-hit colours (weights already include the
    transmittance in front), plus the sky behind."""
    out = np.zeros((n_rays, 3))
    for k in range(3):
        out[:, k] = np.bincount(ray, weight * per_hit[:, k], minlength=n_rays)
    return out + t_after[:, None] * sky


def analyse(stage2, rows):
    import drjit as dr
    import mitsuba as mi
    from mi_invrgbl.eval.metrics import psnr
    from mi_invrgbl.fit import shading_init
    from mi_invrgbl.fit.render import camera_unlit, frozen_gaussian_hits
    from mi_invrgbl.physics.fields import BY_NAME
    from mi_invrgbl.physics.lighting import environment_radiance

    ctx = stage2.ctx
    names = list(ctx.model.nodes)
    colour = np.concatenate([ctx.model.nodes[n].numpy("colour") for n in names]).astype(np.float64)
    albedo = np.concatenate([ctx.model.nodes[n].numpy("albedo") for n in names]).astype(np.float64)
    top, floor = shading_init.clipped_albedo(albedo)
    clipped = top | floor
    spec_mean, _ = stage2.seen_by_cameras(names)
    vals = stage2.values()
    dark = dict(vals)
    for n in names:
        key = "%s.%s" % (n, BY_NAME["albedo"].variable)
        dark[key] = dr.zeros(mi.Float, dr.width(vals[key]))
    frames = [f for f in ctx.selection_frames if f.camera is not None and f.index in stage2.frozen.camera]
    acc = {}

    def add(name, img, f):
        acc.setdefault(name, []).append(psnr(img, f.camera.image.reshape(-1, 3),
                                             mask=f.camera.valid()[:, None], srgb=True))
    share = {"clipped_weight": [], "sky_weight": []}
    with dr.suspend_grad():
        for f in frames:
            fh = stage2.frozen.camera[f.index]
            rays = f.camera.rays

            def per_hit(v):
                nodes = stage2.frozen.nodes(f, v)
                lighting = stage2.lighting(nodes, stage2.frozen.cache(f), frame=f)
                g = frozen_gaussian_hits(nodes, rays, fh)
                c, *_ = ctx.camera_integrator.shade_gaussian_hits(lighting, nodes, rays, fh, g)
                return np.array(c, np.float64).T, lighting
            full, lighting = per_hit(vals)
            spec, _ = per_hit(dark)
            gi = np.array(lighting.table.global_index(fh.node_ids, fh.prims))
            ray = np.array(fh.ray)
            w = np.array(fh.weight, np.float64)
            live = np.array(fh.node_ids) != 0
            w = np.where(live, w, 0.0)
            n = fh.n_rays
            t_after = np.array(fh.t_after, np.float64)
            surface = np.array(fh.surface)
            sky = np.where(surface[:, None], 0.0,
                           np.array(environment_radiance(ctx.scene, rays.d), np.float64).T)
            c1 = colour[gi]
            r_spec = spec - spec_mean[gi]
            r_diff = (full - spec) - (colour - spec_mean)[gi]
            cl = clipped[gi][:, None]
            zero = np.zeros_like(c1)
            add("start (stage 2's render)", np.stack(
                [np.array(x, np.float64) for x in stage2.render_frame(f, vals, lidar=False)
                 ["camera"]["rgb"]], axis=1), f)
            add("start through the cache", composite(ray, w, full, t_after, sky, n), f)
            add("stage 1 through the cache", composite(ray, w, c1, t_after, sky, n), f)
            add("stage 1 + specular residual", composite(ray, w, c1 + r_spec, t_after, sky, n), f)
            add("stage 1 + diffuse residual, clipped Gaussians",
                composite(ray, w, c1 + np.where(cl, r_diff, zero), t_after, sky, n), f)
            add("stage 1 + diffuse residual, unclipped Gaussians",
                composite(ray, w, c1 + np.where(cl, zero, r_diff), t_after, sky, n), f)
            add("start without the specular residual",
                composite(ray, w, full - r_spec, t_after, sky, n), f)
            add("start without the clipped Gaussians' diffuse residual",
                composite(ray, w, full - np.where(cl, r_diff, zero), t_after, sky, n), f)
            valid = f.camera.valid()
            wc = np.bincount(ray, w * clipped[gi], minlength=n)
            share["clipped_weight"].append(float(np.mean(wc[valid])))
            share["sky_weight"].append(float(np.mean(t_after[valid] * ~surface[valid])))
        # Last: stage 1 traced as it scored itself (this pushes the stage-1 model).
        for f in frames:
            idx = np.arange(f.camera.width * f.camera.height)
            ctx.model.push(f.poses, stage=1)
            rgb, _, _ = camera_unlit(ctx.scene, f.camera.pixel_rays(idx), ctx.config.max_hits,
                                     ctx.config.min_transmittance)
            add("stage 1 traced", np.stack([np.array(rgb[c], np.float64) for c in range(3)], axis=1), f)
    seen = spec_mean.any(axis=1)   # (the training views send them light)
    rows["frames"] = [f.index for f in frames]
    rows["psnr"] = {k: float(np.mean(v)) for k, v in acc.items()}
    rows["clipped_share_of_gaussians"] = float(np.mean(clipped))
    rows["clipped_share_of_seen_gaussians"] = float(np.mean(clipped[seen])) if seen.any() else 0.0
    rows["clipped_at_one"] = float(np.mean(top))
    rows["clipped_at_floor"] = float(np.mean(floor))
    rows["clipped_weight_per_pixel"] = float(np.mean(share["clipped_weight"]))
    rows["sky_weight_per_pixel"] = float(np.mean(share["sky_weight"]))


def main():
    args = list(_sys.argv[1:])
    out_json = None
    if "--json" in args:
        i = args.index("--json")
        out_json = args[i + 1]
        del args[i:i + 2]
    if len(args) < 3:
        _sys.exit(__doc__)
    fit, checkpoint, scene, options = args[0], args[1], args[2], args[3:]

    from mi_invrgbl import cli
    from mi_invrgbl.fit.stage2 import Stage2

    rows = {"checkpoint": checkpoint, "scene": scene, "options": options}
    original = Stage2.init_shading

    def record(self):
        report = original(self)
        rows["start"] = {k: report.get(k) for k in ("sun_irradiance", "sun_irradiance_from",
                                                    "light_scale", "start_roughness",
                                                    "specular_share", "unclipped")}
        analyse(self, rows)
        raise Recorded()

    Stage2.init_shading = record
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "fit")
        shutil.copytree(fit, out)
        shutil.copy(checkpoint, os.path.join(out, "checkpoints", "latest.npz"))
        try:
            cli.main(["fit", scene, "-o", out, "--resume"] + options)
        except Recorded:
            pass
    if "psnr" not in rows:
        _sys.exit("the fit ended before stage 2's start")
    print("\nvalidation frames %s; start: %s" % (rows["frames"], json.dumps(rows["start"])))
    print("Gaussians whose albedo clipped: %.1f %% (%.1f %% at 1, %.1f %% at the floor), %.1f %% of "
          "those the cameras see; their blend weight per pixel %.3f; the sky's %.3f"
          % (100 * rows["clipped_share_of_gaussians"], 100 * rows["clipped_at_one"],
             100 * rows["clipped_at_floor"], 100 * rows["clipped_share_of_seen_gaussians"],
             rows["clipped_weight_per_pixel"], rows["sky_weight_per_pixel"]))
    print("| image | validation PSNR [dB] |\n|---|---|")
    for k, v in rows["psnr"].items():
        print("| %s | %.2f |" % (k, v))
    if out_json:
        with open(out_json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
