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

import json
import os
import sys

import numpy as np
import OpenEXR
import cv2
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import drjit as dr  # noqa: E402
import mi_invrgbl  # noqa: E402,F401

LUM = np.array([0.2126, 0.7152, 0.0722])


def exr(path):
    ch = OpenEXR.File(path).channels()
    return ch["RGB"].pixels if "RGB" in ch else next(iter(ch.values())).pixels


def main():
    root, fit = sys.argv[1], sys.argv[2]
    frames = [int(a) for a in sys.argv[3:]] or [1, 8, 13, 18]
    meta = json.load(open(os.path.join(root, "frames.json")))
    gt = meta["ground_truth"]["dir"] if isinstance(meta["ground_truth"], dict) else meta["ground_truth"]
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
        n = int(rec[0].get("source_index", rec[0].get("source_frame", i)))
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
        mesh = size(exr(os.path.join(gt, "maps", "%06d_mesh_id.exr" % n)).squeeze())
        vis = exr(os.path.join(gt, "maps", "%06d_sun_visibility.exr" % n))
        vis = size(vis[..., 0] if vis.ndim == 3 else vis)
        img = cv2.imread(os.path.join(root, "observations", "image_%04d.png" % i))[..., ::-1] / 255.0
        img = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4) @ LUM
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
