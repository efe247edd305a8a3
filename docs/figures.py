"""Regenerate the README/doc pictures of fitted scenes from real runs.

    python docs/figures.py albedo  out/street_fit3 2 out/street_data/gt/maps/000002_albedo.exr [NAME.png]
    python docs/figures.py kitti   out/kitti_fit/fit_full 8 out/street_fit2/fit_full/scene.xml:object_0

``albedo DIR FRAME [GT_ALBEDO.exr [NAME.png]]``: observed image, ground-truth
albedo and sun visibility (next to GT_ALBEDO.exr) and the albedo maps of ``DIR/fit_full``, ``DIR/fit_no_consistency`` and
``DIR/fit_rgb_only`` (written by ``tests/bench/bench_ablation.py``) for one
training frame -> ``docs/img/albedo_ablation.png`` (or NAME.png).

``kitti FIT FRAME OBJECT``: runs ``relight`` (the fitted sun moved to 35 degrees
elevation, with its fitted irradiance, or a new one where the fit has no sun),
``night``, ``insert`` (OBJECT is ``scene.xml:node``) and ``lidar`` on the fitted
scene for one frame and
stacks observed image, relit, night and insertion -> ``docs/img/kitti_fit_apps.png``,
and simulated/observed LiDAR intensity and simulated range ->
``docs/img/kitti_fit_lidar.png``. Every picture is a render of these commands.
"""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
IMG = os.path.join(HERE, "img")


def _cli():
    return [os.path.join(os.path.dirname(sys.executable), "mi-invrgbl")]


def read_exr(path):
    import OpenEXR
    ch = OpenEXR.File(path).channels()
    if "RGB" in ch:
        return ch["RGB"].pixels
    return {k: v.pixels for k, v in ch.items()}


def srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def tile(rgb01, label, width=640):
    im = (np.clip(rgb01, 0, 1) * 255).astype(np.uint8)
    if im.ndim == 2:
        im = np.repeat(im[..., None], 3, -1)
    im = cv2.cvtColor(im, cv2.COLOR_RGB2BGR)
    h = int(round(im.shape[0] * width / im.shape[1]))
    im = cv2.resize(im, (width, h), interpolation=cv2.INTER_AREA)
    cv2.rectangle(im, (0, 0), (width, 20), (0, 0, 0), -1)
    cv2.putText(im, label, (6, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return im


def read_png(path):
    return cv2.imread(path)[..., ::-1] / 255.0


def albedo(root, frame, gt=None, out_name="albedo_ablation.png"):
    rows = [tile(read_png(os.path.join(root, "observations", "image_%04d.png" % frame)),
                 "observed image (training frame %d)" % frame)]
    if gt:
        rows.append(tile(srgb(read_exr(gt)[..., :3]), "ground-truth albedo"))
        vis = gt.replace("_albedo.exr", "_sun_visibility.exr")
        if os.path.isfile(vis):
            v = read_exr(vis)
            v = next(iter(v.values())) if isinstance(v, dict) else v
            v = v[..., 0] if v.ndim == 3 else v
            rows.append(tile(np.clip(v, 0, 1), "ground-truth sun visibility (black: shadow)"))
    for variant, label in (("fit_full", "fitted albedo: full method"),
                           ("fit_no_consistency", "fitted albedo: without the consistency losses"),
                           ("fit_rgb_only", "fitted albedo: RGB only")):
        p = os.path.join(root, variant, "maps", "%04d_albedo.exr" % frame)
        if os.path.isfile(p):
            rows.append(tile(srgb(read_exr(p)[..., :3]), label))
    out = os.path.join(IMG, out_name)
    cv2.imwrite(out, np.vstack(rows))
    print(out)


def _run(args):
    print("$ mi-invrgbl " + " ".join(args), flush=True)
    subprocess.run(_cli() + args, check=True)


def kitti(fit, frame, obj, rerun=True):
    scene = os.path.join(fit, "scene.xml")
    work = os.path.join(fit, "figures")
    sel = ["--frames", "%d:%d" % (frame, frame + 1)]
    if rerun:
        _commands(scene, work, sel, obj)
    _pictures(fit, frame, work)


#: The relit sun's irradiance where the fit found no sun (R, G, B).
NEW_SUN = "3,2.8,2.5"


def has_sun(scene):
    """Whether the scene's light has a sun, read as ``relight`` reads it."""
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from mi_invrgbl.apps.lighting_edit import lighting_of_doc
    from mi_invrgbl.scene.xml import SceneDoc
    lighting = lighting_of_doc(SceneDoc.load(scene))
    return lighting is not None and lighting.has_sun


def _commands(scene, work, sel, obj):
    # The fitted sun moved to 35 degrees keeps its irradiance; a fit without
    # a sun gets one.
    given = [] if has_sun(scene) else ["--sun-irradiance", NEW_SUN]
    _run(["relight", scene, "--sun-elevation", "35", "--sun-azimuth", "-60"] + given
         + ["-o", os.path.join(work, "relight")] + sel)
    _run(["night", scene, "--exposure", "3", "-o", os.path.join(work, "night")] + sel)
    _run(["insert", scene, "--object", obj, "--pose", "9,-1.5,-1.73,0", "-o",
          os.path.join(work, "insert")] + sel)
    _run(["lidar", scene, "-o", os.path.join(work, "lidar")] + sel)


def _pictures(fit, frame, work):
    root = os.path.dirname(os.path.abspath(fit))
    rows = [tile(read_png(os.path.join(root, "observations", "image_%04d.png" % frame)),
                 "KITTI excerpt, frame %d (observed)" % frame, 320)]
    for name, label in (("relight", "fit, relight: a sun at 35 deg elevation"),
                        ("night", "fit, night (exposure x3)"),
                        ("insert", "fit, insert the synthetic street's fitted car")):
        rows.append(tile(read_png(os.path.join(work, name, "frame_%04d.png" % frame)), label, 320))
    out = os.path.join(IMG, "kitti_fit_apps.png")
    cv2.imwrite(out, np.vstack(rows))
    print(out)
    sim = read_exr(os.path.join(work, "lidar", "frame_%04d.exr" % frame))
    obs = read_exr(os.path.join(root, "observations", "lidar_%04d.exr" % frame))
    scale = max(float(np.percentile(obs["intensity"][obs["hit"] > 0], 99)), 1e-6)
    rng = sim["range"]

    def stretch(img):   # 64 beams x 1024 columns: rows repeated to stay readable
        return np.repeat(img, 4, axis=0)
    rows = [tile(stretch(sim["intensity"] / scale), "fit, lidar: simulated intensity (fitted response)", 620),
            tile(stretch(obs["intensity"] / scale), "observed intensity", 620),
            tile(stretch(np.where(rng > 0, 1 - np.clip(rng / 30.0, 0, 1) ** 0.5, 0)),
                 "simulated range (near = bright, 30 m = black)", 620)]
    out = os.path.join(IMG, "kitti_fit_lidar.png")
    cv2.imwrite(out, np.vstack(rows))
    print(out)


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else ""
    if what == "albedo":
        albedo(sys.argv[2], int(sys.argv[3]), sys.argv[4] if len(sys.argv) > 4 else None,
               sys.argv[5] if len(sys.argv) > 5 else "albedo_ablation.png")
    elif what == "kitti":
        kitti(sys.argv[2], int(sys.argv[3]), sys.argv[4], rerun="--pictures-only" not in sys.argv)
    else:
        sys.exit(__doc__)
