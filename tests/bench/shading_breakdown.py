"""How a fitted street splits its radiance into light and albedo, against the truth.

    python tests/bench/shading_breakdown.py SCENE_DIR FIT_DIR [FIT_DIR ...] [--frames 1 8 13 18]

The ground truth's own scene (``gt/scene_time_a.xml``, Mitsuba's ``path``
integrator) is rendered at a few training frames three times: as it is,
without its sun, and with every diffuse reflectance at 0 (specular only).
Each fitted ``scene.xml`` is rendered the same three ways through the
evaluation's pipeline. Per material (ground-truth mesh ids) the table gives
the true and fitted albedo (luminance, median), the share of the radiance
the sun brings (directly or after bounces) and the share that is specular,
and the ratio of the fitted diffuse shading, ``(radiance - specular) /
albedo``, to the true one, divided by that ratio's median over all pixels
(the albedo is only known up to one scale). A material whose ratio is above
1 gets more light in the fit than the truth gives it, relative to the rest
of the scene, and its albedo comes out darker by that factor.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from street_truth import LUM, ground_truth, source_number, truth_map  # noqa: E402
import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.rendering import integrator_like, render_camera  # noqa: E402
from mi_invrgbl.scene.loading import load_scene  # noqa: E402
from mi_invrgbl.synthetic import trajectory  # noqa: E402
from mi_invrgbl.synthetic.rgb_frames import FramePoser  # noqa: E402

#: Materials with fewer scored pixels than this are left out of the table.
MIN_PIXELS = 500
#: Alpha below which a fitted pixel is not scored (mostly sky).
MIN_ALPHA = 0.5


def scaled(params, keys, values, factor):
    """Set every parameter in ``keys`` to its stored value times ``factor``."""
    for k in keys:
        params[k] = values[k] * factor
    params.update()


def truth_renders(gt, numbers, spp):
    """Per frame number: {full, no_sun, specular} linear RGB of the true scene."""
    traj = json.load(open(os.path.join(gt, "trajectory.json")))
    cams = np.asarray(traj["world_from_cam"]) @ trajectory.KITTI_FROM_MITSUBA
    scene = mi.load_file(os.path.join(gt, "scene_time_a.xml"))
    poser = FramePoser(scene, np.asarray(traj["world_from_moving_car"]), ())
    params = mi.traverse(scene)
    diffuse = [k for k in params.keys() if "diffuse_reflectance" in k
               and (k.endswith(".value") or k.endswith(".data"))]
    sun = [k for k in params.keys() if k.startswith("sun.") and k.endswith("irradiance.value")]
    keep = {k: type(params[k])(params[k]) for k in diffuse + sun}
    out = {}
    for n in numbers:
        poser.set_frame(n, cams[n])
        r = {}
        for name, sun_on, diffuse_on in (("full", 1, 1), ("no_sun", 0, 1), ("specular", 1, 0)):
            scaled(params, sun, keep, float(sun_on))
            scaled(params, diffuse, keep, float(diffuse_on))
            r[name] = np.array(mi.render(scene, spp=spp, seed=n), np.float64)[..., :3]
        scaled(params, diffuse + sun, keep, 1.0)
        out[n] = r
    return out


def fit_renders(fit, indices):
    """Per frame index: {full, no_sun, specular, albedo, alpha} of a fitted scene."""
    scene = load_scene(os.path.join(fit, "scene.xml"))
    integ = integrator_like(scene, None)
    params = mi.traverse(scene)
    albedo = [k for k in params.keys() if k.endswith(".albedo")]
    sun = [k for k in params.keys() if k.endswith("sun_irradiance")]
    keep = {k: type(params[k])(dr.detach(params[k])) for k in albedo + sun}
    sensors = {s.id(): s for s in scene.sensors()}
    out = {}
    for i in indices:
        sensor = sensors["camera_%04d" % i]
        full = render_camera(scene, sensor, 0, integ)
        scaled(params, sun, keep, 0.0)
        no_sun = render_camera(scene, sensor, 0, integ)["rgb"]
        scaled(params, sun, keep, 1.0)
        scaled(params, albedo, keep, 0.0)
        specular = render_camera(scene, sensor, 0, integ)["rgb"]
        scaled(params, albedo, keep, 1.0)
        alpha = full["alpha"]
        out[i] = {"full": full["rgb"], "no_sun": no_sun, "specular": specular, "alpha": alpha,
                  "albedo": full["albedo"] / np.maximum(alpha, 1e-3)[..., None]}
    return out


def breakdown(root, fit, indices, truth, gt, names):
    meta = json.load(open(os.path.join(root, "frames.json")))
    by_index = {f["index"]: f for f in meta["frames"]}
    fitted = fit_renders(fit, indices)
    cols = {k: [] for k in ("mesh", "ta", "fa", "tsun", "fsun", "tspec", "fspec", "tshade", "fshade",
                            "tfull", "ffull")}
    for i in indices:
        n = source_number(by_index[i])
        t, f = truth[n], fitted[i]
        mesh = truth_map(gt, "mesh_id", n)
        mesh = np.round(mesh[..., 0] if mesh.ndim == 3 else mesh).astype(int)
        if mesh.shape != f["alpha"].shape:
            raise SystemExit("%s: fitted frames are %s, the truth's %s (fit at the truth's width)"
                             % (fit, f["alpha"].shape, mesh.shape))
        m = (mesh >= 0) & (f["alpha"] > MIN_ALPHA)
        alb = truth_map(gt, "albedo", n)
        lum = lambda x: (x @ LUM)[m]  # noqa: E731
        cols["mesh"].append(mesh[m])
        cols["ta"].append(lum(alb))
        cols["fa"].append(lum(f["albedo"]))
        cols["tfull"].append(lum(t["full"]))
        cols["ffull"].append(lum(f["full"]))
        cols["tsun"].append(lum(t["full"] - t["no_sun"]))
        cols["fsun"].append(lum(f["full"] - f["no_sun"]))
        cols["tspec"].append(lum(t["specular"]))
        cols["fspec"].append(lum(f["specular"]))
        cols["tshade"].append(lum((t["full"] - t["specular"]) / np.maximum(alb, 1e-3)))
        cols["fshade"].append(lum((f["full"] - f["specular"]) / np.maximum(f["albedo"], 1e-3)))
    v = {k: np.concatenate(x) for k, x in cols.items()}
    ratio = v["fshade"] / np.maximum(v["tshade"], 1e-6)
    g = float(np.median(ratio))
    print("\n%s: %d pixels of frames %s; fitted/true diffuse shading, median over all: %.2f"
          % (fit, len(ratio), " ".join(map(str, indices)), g))
    print("| material | pixels | albedo true | albedo fit | sun share true | sun share fit "
          "| specular share true | specular share fit | shading fit/true (/ median) |")
    print("|---|---|---|---|---|---|---|---|---|")
    ids, counts = np.unique(v["mesh"], return_counts=True)
    for mid in ids[np.argsort(-counts)]:
        sel = v["mesh"] == mid
        if sel.sum() < MIN_PIXELS:
            continue
        share = lambda a, b: np.sum(v[a][sel]) / max(np.sum(v[b][sel]), 1e-12)  # noqa: E731
        print("| %s | %d | %.3f | %.3f | %.2f | %.2f | %.2f | %.2f | %.2f |"
              % (names.get(int(mid), str(mid)), sel.sum(), np.median(v["ta"][sel]),
                 np.median(v["fa"][sel]), share("tsun", "tfull"), share("fsun", "ffull"),
                 share("tspec", "tfull"), share("fspec", "ffull"), np.median(ratio[sel]) / g))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", help="the imported street (scene folder with frames.json)")
    ap.add_argument("fits", nargs="+", help="fitted scene folders")
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 8, 13, 18],
                    help="training frame indices (default 1 8 13 18)")
    ap.add_argument("--spp", type=int, default=128, help="samples per pixel of the true renders")
    args = ap.parse_args()
    meta, gt = ground_truth(args.root)
    by_index = {f["index"]: f for f in meta["frames"]}
    missing = [i for i in args.frames if i not in by_index]
    if missing:
        raise SystemExit("%s: no frames %s" % (args.root, missing))
    names = {m["mesh_id"]: m["name"]
             for m in json.load(open(os.path.join(gt, "materials.json")))["meshes"]}
    truth = truth_renders(gt, [source_number(by_index[i]) for i in args.frames], args.spp)
    for fit in args.fits:
        breakdown(args.root, fit, args.frames, truth, gt, names)


if __name__ == "__main__":
    main()
