"""A fitted street's sun visibility and albedo against the truth, split by
sunlit and shadowed pixels (synthetic street).

    python tests/bench/sun_visibility_truth.py FIT_DIR [FIT_DIR ...] [--frames held-out]

Each fitted scene is rendered through the evaluation's pipeline on the
held-out frames (``eval``'s selection, alpha mask and alignment with the
ground truth). Per scored pixel it gathers the fitted albedo (scaled per
channel by one least-squares factor over all pixels pooled, as
``albedo_breakdown.py`` does) and the sun visibility the fit gives the
Gaussians the pixel blends, read through the albedo AOV: once with the
learned field (``sun_visibility``, what the fitted scene's own sun uses),
once with the transmittance traced through the fitted Gaussians towards
the fitted sun (what relight, night and insert use), and once with that
trace cut at 0.5. The truth's maps give the pixel's sun visibility,
albedo and normal.

It prints, for true sunlit (visibility > 0.9) and true shadowed (< 0.1)
pixels facing the true sun (cosine > 0.3; a surface turned away is
unlit whatever its visibility), up-facing (normal z > 0.7) and vertical
(|z| < 0.3): the pixel count, the median and quartiles of fitted over true
albedo luminance (windows left out: their albedo error is the specular
light they show), and the mean of each visibility. Last, the mean
absolute difference of each visibility from the truth's. A median ratio
above 1 in sunlight and below 1 in shadow is light the fit gives the
shadow and takes from the sunlight, whichever of sun level, visibility
or sky term does it.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import ALPHA_MIN, load_lights, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_map  # noqa: E402
from mi_invrgbl.eval.rendering import find_sky, integrator_like, render_camera  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.physics.colour import LUMINANCE  # noqa: E402
from mi_invrgbl.physics.lighting import (GaussianTable, light_at, shadow_origins,  # noqa: E402
                                         transmittance)
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from street_truth import open_fit  # noqa: E402

#: True sun visibility above this is sunlit, below 1 - this shadowed.
LIT = 0.9
#: The true sun's cosine a pixel must have to count (turned away: unlit anyway).
FACING = 0.3


def first_channel(x):
    return x[..., 0] if x is not None and x.ndim == 3 else x


def traced_visibility(scene, nodes):
    """Per node, the transmittance from just above each Gaussian towards the
    scene's sun through the fitted Gaussians (as the integrator traces it)."""
    sky = find_sky(scene)
    table = GaussianTable.build(nodes).load_geometry()
    d, _, _ = light_at("sun", sky, table.center)
    vis = np.clip(np.array(transmittance(scene, shadow_origins(table, d), d, mi.Float(dr.inf),
                                         nodes)), 0.0, 1.0)
    return np.split(vis, np.cumsum([n.count for n in nodes])[:-1])


def collect(fit, frames_spec):
    """Per scored pixel: fitted albedo, true albedo, true visibility, true
    normal, mesh name, and each blended fitted visibility."""
    frames, gt, positions, scene = open_fit(fit, frames_spec)
    integ = integrator_like(scene, None)
    params = mi.traverse(scene)
    nodes = list(hitlib.gaussian_nodes(scene))
    ids = [n.shape.id() for n in nodes]
    albedo = {i: np.array(params[i + ".albedo"]) for i in ids}
    traced = traced_visibility(scene, nodes)
    fields = {"learned": [np.array(params[i + ".sun_visibility"]) for i in ids],
              "traced": traced, "traced > 0.5": [(t > 0.5).astype(np.float32) for t in traced]}
    meshes = json.loads((gt / "materials.json").read_text())["meshes"]
    names = {d["mesh_id"]: d["name"] for d in meshes}
    masks, cols = {}, {k: [] for k in ("fit", "true", "vis", "normal", "name")}
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cam = render_camera(scene, sensor, 0, integ)
        base = str(gt / "maps" / ("%06d_" % source_number(frames[k])))
        mesh = first_channel(read_map(base + "mesh_id.exr"))
        m = (mesh >= 0) & (cam["alpha"] > ALPHA_MIN)
        masks[k] = m
        cols["fit"].append(cam["albedo"][m] / cam["alpha"][m][:, None])
        cols["true"].append(read_map(base + "albedo.exr")[m])
        cols["vis"].append(first_channel(read_map(base + "sun_visibility.exr"))[m])
        cols["normal"].append(read_map(base + "normal.exr")[m])
        cols["name"].append(np.array([names.get(int(i), "?") for i in mesh[m]]))
    out = {k: np.concatenate(v) for k, v in cols.items()}
    # Each visibility through the albedo AOV: the blend of the Gaussians a
    # pixel shows, with the eval's own compositing.
    for label, per_node in fields.items():
        for i, v in zip(ids, per_node):
            params[i + ".albedo"] = mi.Float(np.repeat(v.astype(np.float32), 3))
        params.update()
        got = []
        for k in positions:
            sensor, _ = set_frame(scene, frames, k)
            cam = render_camera(scene, sensor, 0, integ)
            m = masks[k]
            got.append(cam["albedo"][m][:, 0] / cam["alpha"][m])
        out["v " + label] = np.concatenate(got)
    for i in ids:
        params[i + ".albedo"] = mi.Float(albedo[i])
    params.update()
    out["sun"] = np.asarray(load_lights(gt)["time_a"]["sun_direction"], np.float64)
    return out


def report(fit, d):
    p, t = d["fit"], d["true"]
    scale = np.sum(p * t, 0) / np.maximum(np.sum(p * p, 0), 1e-12)
    ratio = ((p * scale) @ LUMINANCE) / np.maximum(t @ LUMINANCE, 1e-3)
    cos = d["normal"] @ d["sun"]
    z = d["normal"][:, 2]
    facing = cos > FACING
    keys = [k for k in d if k.startswith("v ")]
    print("\n%s: %d pixels, %.3f facing the true sun" % (fit, len(p), facing.mean()))
    print("| true sun | surface | pixels | fitted/true albedo median [quartiles] | %s |"
          % " | ".join("%s mean" % k[2:] for k in keys))
    print("|---|---|---|---|%s" % ("---|" * len(keys)))
    not_glass = d["name"] != "windows"
    for lit_name, lit in (("sunlit", d["vis"] > LIT), ("shadowed", d["vis"] < 1 - LIT)):
        for surf_name, surf in (("up-facing", z > 0.7), ("vertical", np.abs(z) < 0.3)):
            sel = facing & lit & surf & not_glass
            if sel.sum() < 50:
                continue
            q = np.percentile(ratio[sel], [25, 50, 75])
            print("| %s | %s | %d | %.2f [%.2f %.2f] | %s |" % (
                lit_name, surf_name, sel.sum(), q[1], q[0], q[2],
                " | ".join("%.2f" % d[k][sel].mean() for k in keys)))
    print("mean |visibility - truth| where facing the true sun: %s" % ", ".join(
        "%s %.3f" % (k[2:], np.mean(np.abs(d[k] - d["vis"])[facing])) for k in keys))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("fits", nargs="+", help="fitted scene folders (fit/)")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    args = ap.parse_args()
    for fit in args.fits:
        report(fit, collect(fit, args.frames))


if __name__ == "__main__":
    main()
