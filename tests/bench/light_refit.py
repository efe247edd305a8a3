"""Is it the fitted light that keeps a street's materials from the truth's?

    python tests/bench/light_refit.py FIT [--albedo VARIANT] [--normals VARIANT] [--roughness VARIANT]
        [--iterations 300] [--every 50] [--hold albedo,normal] [--bounces N] [--json OUT] [--write NAME]

``FIT`` is a finished fit (its ``checkpoints/latest.npz`` and the imported
scene it names). The fit's stage 2 is rebuilt from that checkpoint, as
``fit --resume`` rebuilds it; nothing in ``FIT`` is written. With ``--write NAME`` the result is
written as ``fit`` writes a fit, to a new sibling folder ``FIT_NAME`` (refused
if it exists; written under a temporary name and renamed), for ``eval``. The Gaussians'
albedo is then replaced by the one in ``--albedo VARIANT`` (a fitted scene
folder of the same fit with edited clouds, such as ``albedo_floor.py
--write``'s ``FIT_albedo_floor``) and their normals by ``--normals
VARIANT``'s (``FIT_normal_floor``), and their roughness by ``--roughness
VARIANT``'s (``material_oracle.py --write``'s ``FIT_true_roughness``); the fields named by ``--hold`` are held
there while stage 2 runs ``--iterations`` more steps on the rest: the sky,
the sun's irradiance, the learned sun visibility, the roughness, the LiDAR
albedo and response. Without ``--albedo`` and ``--normals`` the same steps
run from the fit's own materials (the control: what more steps alone give).

``--bounces N`` shades with N diffuse bounces instead of the fit's (the
fitted scene's own count; the sky visibility is traced afresh for it).

Printed every ``--every`` steps: the validation and held-out PSNR of stage
2's own render (``score_stage2``, the lighting caches following the
normals), the fitted sun's irradiance, the sky's mean radiance (its
order-0 term) and the training steps' camera loss
(the mean of the last ``--every`` steps' ``rgb`` term).

Reading: if the held-out PSNR with the held materials climbs back to the
fit's, the light and visibility the fit found are what ask for its
materials (another light draws the images as well with materials near the
truth's); if it stays below, the fit's shading (its BRDF, one bounce,
M sky samples) cannot draw the street with those materials under any light
it can hold. The held-out frames only score; nothing is chosen on them.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.fit.checkpoint import fingerprint, load_checkpoint  # noqa: E402
from mi_invrgbl.fit.config import FitConfig  # noqa: E402
from mi_invrgbl.fit.evaluate import score_stage2  # noqa: E402
from mi_invrgbl.fit.init import load_state  # noqa: E402
from mi_invrgbl.fit.losses import LossWeights  # noqa: E402
from mi_invrgbl.fit import outputs  # noqa: E402
from mi_invrgbl.fit.runner import freeze  # noqa: E402
from mi_invrgbl.fit.variables import GaussianVariable  # noqa: E402
from mi_invrgbl.physics.fields import BY_NAME  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402
from mi_invrgbl.physics import sh as sh_basis  # noqa: E402
from normal_oracle import variant_folder  # noqa: E402
from street_truth import refuse_existing, write_json  # noqa: E402

#: Fields a variant may replace: the fit's name -> the cloud's attribute.
REPLACEABLE = {"albedo": "albedo", "normal": "normals", "roughness": "roughness"}


def read_meta(fit):
    path = os.path.join(fit, "checkpoints", "latest.npz")
    if not os.path.isfile(path):
        raise SystemExit("%s: no checkpoint (a finished fit keeps checkpoints/latest.npz)" % fit)
    meta = json.loads(bytes(np.load(path)["meta"]).decode())
    if meta.get("stage") != "done":
        raise SystemExit("%s: the checkpoint is of an unfinished fit (%s)" % (path, meta.get("stage")))
    return meta


def fit_config(fit, meta):
    """The fit's configuration, pointed at ``fit`` (read only: a checkpoint is never written)."""
    saved = dict(meta["config"])
    saved["weights"] = LossWeights(**saved["weights"])
    known = set(FitConfig.__dataclass_fields__)
    config = FitConfig(**{k: v for k, v in saved.items() if k in known})
    config.output = os.path.abspath(fit)
    config.resume = True
    return config


def open_stage2(fit, bounces=None):
    """``(state, stage2)``: the finished fit's stage 2, rebuilt from its
    checkpoint (shading with ``bounces`` diffuse bounces if given, else the fit's)."""
    meta = read_meta(fit)
    try:
        metrics = json.loads(open(os.path.join(fit, "metrics.json")).read())
        # ``fit`` names its imported scene at the top; ``eval`` moves the
        # fit's record under "fit" and names the fitted scene there.
        scene_path = metrics["fit"]["scene"] if "fit" in metrics else metrics["scene"]
    except (OSError, ValueError, KeyError, TypeError):
        raise SystemExit("%s: metrics.json names no imported scene" % fit) from None
    config = fit_config(fit, meta)
    state = load_state(scene_path, config, log=lambda *a: None)
    # load_checkpoint restores the progress log's rows into this (nothing is written).
    state.speed_log = SimpleNamespace(rows=[])
    load_checkpoint(state, fingerprint(state))
    if bounces is not None:
        # After the checkpoint's fingerprint check, which the fit's own count passed.
        state.config.bounces = int(bounces)
    stage2, _ = freeze(state, initialise=False)
    return state, stage2


def replace_field(state, variant, name):
    """Set every node's ``name`` field to ``variant``'s clouds (same Gaussians, same order)."""
    field = BY_NAME[name]
    for node_name, node in state.model.nodes.items():
        path = os.path.join(variant, node_name + ".ply")
        if not os.path.isfile(path):
            raise SystemExit("%s: missing (the variant must hold every node's cloud)" % path)
        values = np.asarray(getattr(read_ply(path), REPLACEABLE[name]), np.float64)
        if len(values) != node.count:
            raise SystemExit("%s: %d Gaussians, the fit's node '%s' %d"
                             % (path, len(values), node_name, node.count))
        node.values[field.variable] = mi.Float(np.ascontiguousarray(field.to_storage(values), np.float32).ravel())


def write_fit(state, stage2, target):
    """The stage's result as ``fit`` writes one, in a temporary folder renamed to ``target``."""
    import shutil
    import tempfile
    stage2.commit()
    stage2.refresh_lighting()
    tmp = tempfile.mkdtemp(prefix=os.path.basename(target) + ".", dir=os.path.dirname(target) or ".")
    try:
        state.config.output = tmp
        state.t_start = time.perf_counter()
        outputs.write_outputs(state, stage2)
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def sky_radiance(state):
    """The fitted sky's mean radiance (its order-0 term), RGB."""
    sh = np.array(dr.detach(state.params[state.sky_key]), np.float64).ravel()
    return np.round(sh[:3] * sh_basis.Y0, 4).tolist()


def sun_irradiance(state):
    return np.round(np.array(dr.detach(state.params[state.sun_key]), np.float64).ravel(), 3).tolist()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="a finished fit's folder")
    ap.add_argument("--albedo", help="fitted-scene folder whose clouds' albedo replaces the fit's")
    ap.add_argument("--normals", help="fitted-scene folder whose clouds' normals replace the fit's")
    ap.add_argument("--roughness", help="fitted-scene folder whose clouds' roughness replaces the fit's "
                    "(e.g. material_oracle.py --write's FIT_true_roughness)")
    ap.add_argument("--hold", default="albedo,normal",
                    help="fields held where they start (comma-separated: albedo, normal, roughness, "
                         "sun_visibility, lidar_albedo)")
    ap.add_argument("--iterations", type=int, default=300, help="stage-2 steps to run")
    ap.add_argument("--every", type=int, default=50, help="score every this many steps")
    ap.add_argument("--bounces", type=int,
                    help="shade with this many diffuse bounces instead of the fit's (its sky visibility "
                         "and bounce matrix are traced afresh)")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--write", metavar="NAME",
                    help="write the result as a fitted scene next to the fit (FIT_NAME), for eval")
    args = ap.parse_args()
    refuse_existing(args.json)
    hold = {h.strip() for h in args.hold.split(",") if h.strip()}
    unknown = hold - set(BY_NAME)
    if unknown:
        raise SystemExit("--hold: unknown field(s) %s" % ", ".join(sorted(unknown)))

    target = None
    if args.write:
        target = variant_folder(args.fit, args.write)
        if os.path.exists(target):
            raise SystemExit("%s: exists; not overwritten" % target)
    t0 = time.perf_counter()
    state, stage2 = open_stage2(args.fit, args.bounces)
    fitted = score_stage2(stage2, state.held_out_frames, refresh=True)
    if args.albedo:
        replace_field(state, args.albedo, "albedo")
    if args.normals:
        replace_field(state, args.normals, "normal")
        # The lighting caches' sky directions turn with the normals.
        stage2.lighting_stale = True
    if args.roughness:
        replace_field(state, args.roughness, "roughness")
    stage2.build_optimizer(only=lambda v: not (isinstance(v, GaussianVariable) and v.field.name in hold))
    freed = sorted(stage2.opt.variables)
    print("%s: rebuilt in %.0f s; held-out PSNR as fitted %.2f dB; held %s; optimised %d arrays"
          % (args.fit, time.perf_counter() - t0, fitted[0], ",".join(sorted(hold)) or "nothing",
             len(freed)), flush=True)
    print("| step | validation PSNR [dB] | held-out PSNR [dB] | sun irradiance | sky mean radiance | training camera loss | s |")
    print("|---|---|---|---|---|---|---|")
    rows, losses, t = [], [], time.perf_counter()
    for it in range(args.iterations + 1):
        if it % args.every == 0 or it == args.iterations:
            val = score_stage2(stage2, state.validation_frames, refresh=True)[0]
            held = score_stage2(stage2, state.held_out_frames)[0]
            row = {"step": it, "validation_psnr": round(val, 3), "held_out_psnr": round(held, 3),
                   "sun_irradiance": sun_irradiance(state), "sky_radiance": sky_radiance(state),
                   "training_rgb_loss": round(float(np.mean(losses[-args.every:])), 5) if losses else None,
                   "seconds": round(time.perf_counter() - t, 1)}
            rows.append(row)
            print("| %d | %.2f | %.2f | %s | %s | %s | %.0f |" % (
                it, val, held, row["sun_irradiance"], row["sky_radiance"],
                "-" if row["training_rgb_loss"] is None else "%.4f" % row["training_rgb_loss"],
                row["seconds"]), flush=True)
        if it == args.iterations:
            break
        total, terms, _ = stage2.iteration(it)
        losses.append(terms.get("rgb", total))
    if target:
        write_fit(state, stage2, target)
        print("written: %s" % target)
    if args.json:
        write_json(args.json, {"fit": args.fit, "albedo": args.albedo, "normals": args.normals, "roughness": args.roughness,
                       "bounces": state.config.bounces,
                       "hold": sorted(hold), "fitted_held_out_psnr": round(fitted[0], 3),
                       "rows": rows})


if __name__ == "__main__":
    main()
