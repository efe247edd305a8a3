"""How a fitted street carries the truth's own light, term by term (synthetic street).

    python tests/bench/transport_breakdown.py FIT_DIR [FIT_DIR ...] [--frames held-out] [--spp 64] [--json OUT]

Given right materials (``light_refit.py --write`` with the albedo and
normals ``albedo_floor.py --write`` solves held), a fit's stage 2 can still
ask for a light far from the truth's (a sun 1.4-1.8x and a sky 0.5-0.6x
on the main job's coated fit, before the coat's bounce): under the truth's
light its shadowed surfaces come out too bright against its sunlit ones.
This script finds which part of the shading does that. The truth's scene
(``gt/scene_time_a.xml``, Mitsuba's ``path``) and the fitted scene with the
truth's time-A light put on its ``shsun`` emitter (set as ``eval`` sets the
time-B light; the sun's shadows traced) are each rendered at the selected
frames with one light at a time and one kind of transport at a time:

- ``sky``: the sky alone, every bounce (the truth: ``max_depth`` 4, as its
  images; the fit: its own ``bounces``);
- ``sky direct``: the sky alone, no light after a bounce (the truth:
  ``max_depth`` 2; the fit: ``bounces`` 0);
- ``sky specular``: the sky alone, direct, every diffuse reflectance (the
  truth) or albedo (the fit) at 0: the sky's reflection off the surfaces' coat;
- ``sun`` and ``sun direct``: the same for the sun alone;
- ``sun learned``: the fit's sun through its learned visibility field (as
  the fitted scene renders itself), against the truth's ``sun``.

Per ground-truth material (mesh ids) the table gives the truth's mean
luminance of each term and the fit's against it (fitted/true). With right
albedo, a term whose ratio is far from 1 is transport the fit gets wrong:
``sky direct`` the sky's visibility and the coat, ``sky - sky direct`` the
bounce, ``sky specular`` the reflection, ``sun direct`` the sun's shadows.
The last line is every scored pixel. Pixels the fit leaves mostly empty
(alpha < 0.5) and the moving car are not scored.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parent))
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import xml.etree.ElementTree as ET  # noqa: E402
from collections import namedtuple  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import gt_alignment, load_lights, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_map  # noqa: E402
from mi_invrgbl.eval.rendering import SkySwap, find_sky, render_camera  # noqa: E402
from mi_invrgbl.eval.scoring import EVAL_SPP  # noqa: E402
from mi_invrgbl.physics.colour import LUMINANCE  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from mi_invrgbl.synthetic import trajectory  # noqa: E402
from mi_invrgbl.synthetic.rgb_frames import FramePoser  # noqa: E402
from shading_breakdown import scaled  # noqa: E402
from street_truth import open_fit, refuse_existing, write_json  # noqa: E402

#: The terms: name, the light on ("sky" / "sun"), bounces on, diffuse on,
#: and (the fit only) the sun's learned visibility instead of its traced one.
Term = namedtuple("Term", "name light bounce diffuse learned")
TERMS = (Term("sky", "sky", True, True, False), Term("sky direct", "sky", False, True, False),
         Term("sky specular", "sky", False, False, False), Term("sun", "sun", True, True, False),
         Term("sun direct", "sun", False, True, False),
         Term("sun learned", "sun", True, True, True))
#: Materials below this share of the scored pixels are pooled into "other".
MIN_SHARE = 0.01
#: Alpha below which a fitted pixel is not scored.
MIN_ALPHA = 0.5


def truth_terms(gt, numbers, spp):
    """Per frame number and term: the truth's linear RGB (H*W, 3)."""
    traj = json.loads((gt / "trajectory.json").read_text())
    cams = np.asarray(traj["world_from_cam"]) @ trajectory.KITTI_FROM_MITSUBA
    xml = gt / "scene_time_a.xml"
    scene = mi.load_file(str(xml))
    # The path length the truth's images were rendered with (Mitsuba's
    # integrator does not expose it).
    depth = ET.parse(xml).getroot().find("integrator/integer[@name='max_depth']")
    if depth is None:
        raise SystemExit("%s: no max_depth on its integrator" % xml)
    integ = {True: mi.load_dict({"type": "path", "max_depth": int(depth.get("value"))}),
             False: mi.load_dict({"type": "path", "max_depth": 2})}
    poser = FramePoser(scene, np.asarray(traj["world_from_moving_car"]), ())
    params = mi.traverse(scene)
    diffuse = [k for k in params.keys() if "diffuse_reflectance" in k
               and (k.endswith(".value") or k.endswith(".data"))]
    sun = [k for k in params.keys() if k.startswith("sun.") and k.endswith("irradiance.value")]
    sky = [k for k in params.keys() if k.startswith("sky.") and k.endswith("radiance.value")]
    if not sun or not sky:
        raise SystemExit("%s: the truth has no 'sun' directional and 'sky' constant emitter" % gt)
    saved = {k: type(params[k])(params[k]) for k in diffuse + sun + sky}
    out = {}
    try:
        for n in numbers:
            poser.set_frame(n, cams[n])
            out[n] = {}
            for term in TERMS:
                if term.learned:  # the truth has no learned field: its "sun"
                    out[n][term.name] = out[n]["sun"]
                    continue
                scaled(params, sun, saved, float(term.light == "sun"))
                scaled(params, sky, saved, float(term.light == "sky"))
                scaled(params, diffuse, saved, float(term.diffuse))
                img = mi.render(scene, integrator=integ[term.bounce], spp=spp, seed=n)
                out[n][term.name] = np.array(img, np.float64)[..., :3].reshape(-1, 3)
    finally:
        scaled(params, diffuse + sun + sky, saved, 1.0)
    return out


def fit_terms(scene, frames, positions, light, R, spp):
    """Per frame position and term: the fit's linear RGB under the truth's
    ``light`` (lights.json's time A), and its alpha."""
    sky = find_sky(scene)
    if sky is None:
        raise SystemExit("no shsun emitter in the fitted scene")
    own = scene.integrator()
    integ = {(b, learned): mi.load_dict(dict(own.settings(),
                                             sun_visibility="attribute" if learned else "trace",
                                             bounces=own.bounces if b else 0))
             for b in (True, False) for learned in (True, False)}
    params = mi.traverse(scene)
    albedo = [k for k in params.keys() if k.endswith(".albedo")]
    saved = {k: type(params[k])(dr.detach(params[k])) for k in albedo}
    swap = SkySwap(sky)
    sun_dir = R @ np.asarray(light["sun_direction"], np.float64)
    out = {}
    try:
        for k in positions:
            sensor, _ = set_frame(scene, frames, k)
            out[k] = {}
            for term in TERMS:
                swap.set(light["sky_radiance"] if term.light == "sky" else [0, 0, 0], sun_dir,
                         light["sun_irradiance"] if term.light == "sun" else [0, 0, 0])
                scaled(params, albedo, saved, float(term.diffuse))
                r = render_camera(scene, sensor, spp, integ[term.bounce, term.learned])
                out[k][term.name] = r["rgb"].reshape(-1, 3)
                out[k]["alpha"] = r["alpha"].reshape(-1)
    finally:
        scaled(params, albedo, saved, 1.0)
        swap.restore()
    return out


def report(fit, truth, fitted, frames, positions, gt, names):
    lum = {term.name: ([], []) for term in TERMS}
    labels = []
    for k in positions:
        n = source_number(frames[k])
        mesh = read_map(str(gt / "maps" / ("%06d_mesh_id.exr" % n)))
        mesh = np.round((mesh[..., 0] if mesh.ndim == 3 else mesh).reshape(-1)).astype(int)
        keep = (mesh >= 0) & (fitted[k]["alpha"] > MIN_ALPHA)
        label = np.array([names.get(int(i), str(i)) for i in mesh[keep]])
        keep_idx = np.flatnonzero(keep)[label != "moving_car"]
        labels.append(label[label != "moving_car"])
        for name in lum:
            lum[name][0].append(truth[n][name][keep_idx] @ LUMINANCE)
            lum[name][1].append(fitted[k][name][keep_idx] @ LUMINANCE)
    label = np.concatenate(labels)
    t = {k: np.concatenate(v[0]) for k, v in lum.items()}
    f = {k: np.concatenate(v[1]) for k, v in lum.items()}
    kinds, counts = np.unique(label, return_counts=True)
    kinds = list(kinds[np.argsort(-counts)])
    small = [n for n in kinds if np.mean(label == n) < MIN_SHARE]
    rows = [n for n in kinds if n not in small] + (["other"] if small else []) + ["all"]
    print("\n%s: %d pixels; per term the truth's mean luminance and the fit's / the truth's"
          % (fit, len(label)))
    print("| material | pixels | " + " | ".join("%s: true | fit/true" % t.name for t in TERMS)
          + " | bounce (sky): true | fit/true |")
    print("|---|---|" + "---|---|" * (len(TERMS) + 1))
    table = {}
    for name in rows:
        sel = np.isin(label, small) if name == "other" else (
            np.ones(len(label), bool) if name == "all" else label == name)
        cells, entry = [], {"pixels": float(sel.mean())}
        for term in [t.name for t in TERMS] + ["bounce"]:
            if term == "bounce":
                tm = np.mean(t["sky"][sel] - t["sky direct"][sel])
                fm = np.mean(f["sky"][sel] - f["sky direct"][sel])
            else:
                tm, fm = np.mean(t[term][sel]), np.mean(f[term][sel])
            ratio = fm / tm if abs(tm) > 1e-6 else float("nan")
            entry[term] = {"true": float(tm), "fit": float(fm)}
            cells.append("%.4f | %.2f" % (tm, ratio))
        table[name] = entry
        print("| %s | %.3f | %s |" % (name, sel.mean(), " | ".join(cells)))
    return table


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fits", nargs="+", help="fitted scene folders")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of the truth's renders "
                    "(the fit's: eval's, %d)" % EVAL_SPP)
    ap.add_argument("--json", help="write the tables here")
    args = ap.parse_args()
    refuse_existing(args.json)
    truth, out = None, {}
    for fit in args.fits:
        frames, gt, positions, scene = open_fit(fit, args.frames)
        light = load_lights(gt).get("time_a")
        if light is None:
            raise SystemExit("%s: lights.json has no time_a light" % gt)
        R = gt_alignment(frames, positions, gt)
        if truth is None:
            truth = truth_terms(gt, [source_number(frames[k]) for k in positions], args.spp)
        fitted = fit_terms(scene, frames, positions, light, R, EVAL_SPP)
        names = {d["mesh_id"]: d["name"]
                 for d in json.loads((gt / "materials.json").read_text())["meshes"]}
        out[fit] = report(fit, truth, fitted, frames, positions, gt, names)
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
