"""Where a fitted street's ground radiance comes from (synthetic street).

    python tests/bench/shading_decomposition.py out/street_fit3 fit_full [frame ...]

The fitted ``scene.xml`` is rendered through the standard pipeline for a few
training frames four times: as fitted, without the sun, with zero albedo
(specular only) and with zero albedo and no sun (the sky's specular
reflection). Median luminance over road and sidewalk pixels (ground-truth
mesh ids), split by the ground truth's sun visibility, is printed next to the
observed image. Where the sky's specular reflection alone reaches the
observed shadow, the fit can only explain the shadow with near-zero albedo.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import json
import os
import sys

import numpy as np
import cv2
import mitsuba as mi

from street_truth import LUM, ground_truth, observed_linear, source_number, truth_map
import drjit as dr  # noqa: E402
import mi_invrgbl  # noqa: E402,F401


def main():
    root, fit = sys.argv[1], sys.argv[2]
    frames = [int(a) for a in sys.argv[3:]] or [1, 8, 13, 18]
    meta, gt = ground_truth(root)
    ids = {m["name"]: m["mesh_id"] for m in json.load(open(os.path.join(gt, "materials.json")))["meshes"]}
    scene = mi.load_file(os.path.join(root, fit, "scene.xml"), spp=16)
    params = mi.traverse(scene)
    albedo = {k: dr.detach(params[k]) for k in params.keys() if k.endswith(".albedo")}
    sun = mi.Color3f(params["sky.sun_irradiance"])
    rows = {}
    for i in frames:
        rec = [f for f in meta["frames"] if f["index"] == i]
        sensor = [s for s in scene.sensors() if s.id() == "camera_%04d" % i]
        if not rec or not sensor:
            continue
        n = source_number(rec[0])
        renders = {}
        for name, no_sun, no_albedo in (("fitted", False, False), ("no sun", True, False),
                                        ("specular", False, True), ("sky specular", True, True)):
            params["sky.sun_irradiance"] = mi.Color3f(1e-6) if no_sun else sun
            for k, v in albedo.items():
                params[k] = dr.zeros(mi.Float, dr.width(v)) if no_albedo else v
            params.update()
            renders[name] = np.array(mi.render(scene, sensor=sensor[0], spp=16))[..., :3] @ LUM
        H, W = renders["fitted"].shape
        size = lambda x: cv2.resize(x.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST)  # noqa: E731
        mesh = size(truth_map(gt, "mesh_id", n))
        vis = size(truth_map(gt, "sun_visibility", n))
        img = observed_linear(root, i) @ LUM
        img = size(img) if img.shape != (H, W) else img
        for surface in ("road", "sidewalk"):
            for light, m in (("shadow", vis < 0.5), ("sunlit", vis >= 0.5)):
                sel = (np.round(mesh) == ids[surface]) & m
                r = rows.setdefault((surface, light), {k: [] for k in ["observed"] + list(renders)})
                r["observed"].append(img[sel])
                for k, v in renders.items():
                    r[k].append(v[sel])
    print("| surface | sun | pixels | observed | fitted | no sun | specular | sky specular |")
    print("|---|---|---|---|---|---|---|---|")
    for (surface, light), r in rows.items():
        v = {k: np.concatenate(x) for k, x in r.items()}
        if v["observed"].size == 0:
            continue
        print("| %s | %s | %d | %s |" % (surface, light, v["observed"].size, " | ".join(
            "%.4f" % np.median(v[k]) for k in ("observed", "fitted", "no sun", "specular", "sky specular"))))


if __name__ == "__main__":
    main()
