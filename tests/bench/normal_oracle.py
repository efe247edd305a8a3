"""Where a fitted street's normal error comes from: the Gaussians' normals,
or Gaussians away from every true surface (synthetic street).

    python tests/bench/normal_oracle.py FIT_DIR [--spp 32] [--off 0.2] [--png OUT.png] [--write]

The fitted scene is rendered on ``eval``'s held-out frames, as ``eval``
renders them (its samples per pixel and alpha mask), four times:

* ``fit``: as fitted;
* ``true normals``: every background Gaussian within ``--off`` metres of a
  true surface takes that surface's normal (the closest of 3 million points
  sampled on the truth's static meshes; sign kept from the fitted one);
* ``on-surface only``: background Gaussians farther than ``--off`` from
  every true surface get opacity 0 (the rest keep their fitted normals);
* ``both``.

First line: the truth's own meshes traced with ``eval``'s samples per
pixel (jittered over each pixel, averaged as the box filter does) against
the truth's maps (one ray through each pixel's centre): what a fit whose
geometry were the truth's would score, the metric's floor. Each row splits
the mean normal error as ``albedo_breakdown.py`` does: pixels at the
truth's edges, tree crowns off them, and the rest. Before the table,
the Gaussians themselves: how many stand off the truth's surfaces, and the
angle of their normals to the closest surface's. The moving car's Gaussians
are left as fitted. A row far below ``fit`` names what holds the normals
back: ``true normals`` the normals learned on the right surfaces,
``on-surface only`` the Gaussians the truth does not have. With ``--png``
the first two scored frames are drawn: the image, the truth's normals, then
each variant's normal map and its error (0-60 degrees, blue to red). With
``--write`` each changed variant is also written as a fitted scene next to
the fit (``FIT_DIR_true_normals``, ``FIT_DIR_on_surface_only``,
``FIT_DIR_both``: its scene files with the edited ``background.ply``) for
``mi-invrgbl eval`` to score in full (relighting, albedo, PSNR); an
existing folder of that name is left alone and the run stops.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import mitsuba as mi  # noqa: E402
import trimesh  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import ALPHA_MIN, gt_alignment, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_map  # noqa: E402
from mi_invrgbl.eval.rendering import integrator_like, render_camera  # noqa: E402
from mi_invrgbl.eval.scoring import EVAL_SPP  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import read_ply, write_ply  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from street_truth import nearest_points, open_fit, truth_to_scene  # noqa: E402
from albedo_breakdown import first_channel, truth_edges  # noqa: E402

#: A pixel whose fitted depth is within this fraction of the truth's shows
#: the same surface as the truth's pixel.
SAME_DEPTH = 0.05
#: Points sampled on the truth's static meshes (about 6 cm apart on the street).
SAMPLES = 3_000_000


def truth_surface(gt, frames, positions):
    """``(points, normals)`` sampled on the truth's static meshes, in the
    scene's world (the first scored frame's camera pose maps them)."""
    meshes = json.loads((gt / "materials.json").read_text())["meshes"]
    parts = [trimesh.load(str(gt / "meshes" / (d["name"] + ".ply")), process=False)
             for d in meshes if not d.get("dynamic") and (gt / "meshes" / (d["name"] + ".ply")).is_file()]
    mesh = trimesh.util.concatenate(parts)
    points, faces = trimesh.sample.sample_surface(mesh, SAMPLES, seed=0)
    T = truth_to_scene(gt, frames[positions[0]])
    return points @ T[:3, :3].T + T[:3, 3], mesh.face_normals[faces] @ T[:3, :3].T


def z_per_unit_distance(sensor, width, height, directions=None):
    """Per pixel: camera-space depth per unit of distance along the centre
    ray (the truth's depth maps are camera z, the depth AOV a distance).
    ``directions``: the centre rays' (H*W, 3) directions where the caller
    has them already (else traced from the sensor)."""
    from mi_invrgbl.synthetic.groundtruth import camera_rays, rows
    d = rows(camera_rays(sensor, width, height).d) if directions is None else \
        np.asarray(directions, np.float64).reshape(-1, 3)
    forward = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)[:3, 2]
    return (d @ (forward / np.linalg.norm(forward))).reshape(height, width)


def truth_floor(gt, numbers, spp, seed=0):
    """Mean normal error [deg] of the truth's meshes averaged over ``spp``
    jittered rays per pixel against its centre-ray maps, and its share at
    the truth's edges."""
    from mi_invrgbl.physics.host_arrays import jit_array
    from mi_invrgbl.synthetic import groundtruth, rgb_frames, trajectory
    info = json.loads((gt / "trajectory.json").read_text())
    cams = np.asarray(info["world_from_cam"], np.float64)
    w, h = info["width"], info["height"]
    scene = mi.load_file(str(gt / "scene_time_a.xml"))
    poser = rgb_frames.FramePoser(scene, np.asarray(info["world_from_moving_car"], np.float64))
    rng = np.random.default_rng(seed)
    angle, edge = [], []
    for i in numbers:
        poser.set_frame(i, cams[i] @ trajectory.KITTI_FROM_MITSUBA)
        sensor = scene.sensors()[0]
        total = np.zeros((h * w, 3))
        for _ in range(spp):
            u = (np.arange(w)[None, :] + rng.random((h, w))) / w
            v = (np.arange(h)[:, None] + rng.random((h, w))) / h
            pos = mi.Point2f(jit_array(mi.Float, u.ravel()), jit_array(mi.Float, v.ravel()))
            ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
            si = scene.ray_intersect(ray)
            n = groundtruth.oriented_normals(groundtruth.rows(si.n), groundtruth.rows(ray.d))
            total += np.where(np.array(si.is_valid(), bool)[:, None], n, 0.0)
        base = str(gt / "maps" / ("%06d_" % i))
        mesh = first_channel(read_map(base + "mesh_id.exr"))
        true_map = read_map(base + "normal.exr")
        m = mesh >= 0
        n = total.reshape(h, w, 3)[m]
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        angle.append(np.degrees(np.arccos(np.clip(np.sum(n * true_map[m], 1), -1.0, 1.0))))
        edge.append(truth_edges(mesh, true_map)[m])
    a, e = np.concatenate(angle), np.concatenate(edge)
    return a.mean(), a[e].mean(), a[e].sum() / len(a)


def normal_error(scene, frames, positions, gt, spp):
    """Per scored pixel: normal error [deg], on a truth edge, in a tree
    crown, and whether the fitted depth is within ``SAME_DEPTH`` of the truth's."""
    integ = integrator_like(scene, None)
    R = gt_alignment(frames, positions, gt)
    meshes = json.loads((gt / "materials.json").read_text())["meshes"]
    crown_ids = [d["mesh_id"] for d in meshes if d["name"] == "tree_crown"]
    angle, edge, crown, same, pictures = [], [], [], [], []
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cam = render_camera(scene, sensor, spp, integ)
        base = str(gt / "maps" / ("%06d_" % source_number(frames[k])))
        mesh = first_channel(read_map(base + "mesh_id.exr"))
        true_map = read_map(base + "normal.exr")
        m = (mesh >= 0) & (cam["alpha"] > ALPHA_MIN)
        n = cam["normal"][m]
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        cos = np.sum(n * (true_map[m] @ R.T), axis=1)
        angle.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        edge.append(truth_edges(mesh, true_map)[m])
        crown.append(np.isin(mesh, crown_ids)[m])
        h, w = mesh.shape
        z = cam["depth"] / np.maximum(cam["alpha"], 1e-6) * z_per_unit_distance(sensor, w, h)
        true_z = first_channel(read_map(base + "depth.exr"))
        same.append((np.abs(z - true_z) <= SAME_DEPTH * true_z)[m])
        if len(pictures) < 2:
            full = np.zeros(mesh.shape)
            full[m] = angle[-1]
            pictures.append((cam["rgb"], true_map @ R.T, cam["normal"], full))
    return tuple(np.concatenate(v) for v in (angle, edge, crown, same)) + (pictures,)


def draw(pictures_by_variant, path):
    """Rows: image, truth's normals, then per variant its normals and error;
    one column per frame."""
    def normals(n):
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        return (np.clip(n * 0.5 + 0.5, 0, 1) * 255).astype(np.uint8)[..., ::-1]

    def error(a):
        return cv2.applyColorMap(np.clip(a / 60.0 * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)

    first = next(iter(pictures_by_variant.values()))
    columns = []
    for j in range(len(first)):
        rgb, truth = first[j][0], first[j][1]
        rows = [(np.clip(rgb, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)[..., ::-1], normals(truth)]
        for pics in pictures_by_variant.values():
            rows += [normals(pics[j][2]), error(pics[j][3])]
        columns.append(np.concatenate(rows, 0))
    out = np.concatenate(columns, 1)
    cv2.imwrite(path, out, [cv2.IMWRITE_PNG_COMPRESSION, 9])


#: Files of a fit folder a written variant keeps (with its own background.ply).
SCENE_FILES = ("scene.xml", "scene_lidar.xml", "frames.json")


def variant_folder(fit, name):
    """Where ``--write`` puts variant ``name`` of ``fit``."""
    return "%s_%s" % (os.path.normpath(fit), name.replace(" ", "_").replace("-", "_"))


def write_variant(fit, name, normals, opacities):
    """The fit's scene with the background's normals and opacities replaced
    (:func:`write_edited`)."""
    def edit(cloud):
        if len(normals) != len(cloud.centers) or len(opacities) != len(cloud.centers):
            raise ValueError("%s: %d normals and %d opacities for %d Gaussians"
                             % (fit, len(normals), len(opacities), len(cloud.centers)))
        cloud.normals = np.asarray(normals, np.float32)
        # A logit-stored opacity of exactly 0 would be -inf in the file.
        cloud.opacities = np.maximum(np.asarray(opacities, np.float32), 1e-6)
    return write_edited(fit, name, edit)


def write_edited(fit, name, edit):
    """The fit's scene with ``edit(cloud)`` applied to its ``background.ply``
    (or, with ``edit`` a dict ``{ply file name: edit}``, to each cloud it
    names), as a sibling folder (same depth, so frames.json's relative paths
    hold); written under a temporary name and renamed into place."""
    import glob
    import shutil
    import tempfile
    target = variant_folder(fit, name)
    if os.path.exists(target):
        raise SystemExit("%s: exists; not overwritten" % target)
    edits = edit if isinstance(edit, dict) else {"background.ply": edit}
    tmp = tempfile.mkdtemp(prefix=os.path.basename(target) + ".", dir=os.path.dirname(fit) or ".")
    try:
        for f in list(SCENE_FILES) + [os.path.basename(p) for p in glob.glob(os.path.join(fit, "*.ply"))]:
            if os.path.isfile(os.path.join(fit, f)) and f not in edits:
                shutil.copy2(os.path.join(fit, f), os.path.join(tmp, f))
        for f, change in edits.items():
            cloud = read_ply(os.path.join(fit, f))
            change(cloud)
            write_ply(os.path.join(tmp, f), cloud)
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="fitted scene folder (fit/)")
    ap.add_argument("--spp", type=int, default=EVAL_SPP, help="camera samples per pixel (eval's)")
    ap.add_argument("--off", type=float, default=0.2,
                    help="metres from the closest true surface beyond which a Gaussian is off it")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    ap.add_argument("--png", help="draw the first two frames' normal maps and errors here")
    ap.add_argument("--write", action="store_true",
                    help="also write each changed variant as a fitted scene next to the fit (for eval)")
    args = ap.parse_args()

    # Refused before the renders, not after them.
    taken = [variant_folder(args.fit, v) for v in ("true normals", "on-surface only", "both")
             if args.write and os.path.exists(variant_folder(args.fit, v))]
    if taken:
        raise SystemExit("%s: exists; not overwritten" % taken[0])
    frames, gt, positions, scene = open_fit(args.fit, args.frames)
    floor = truth_floor(gt, [source_number(frames[k]) for k in positions], args.spp)
    print("the truth's meshes at %d samples per pixel: %.2f deg (at its edges %.1f, %.2f of the mean)"
          % ((args.spp,) + floor), flush=True)
    params = mi.traverse(scene)
    normal0 = np.array(params["background.normal"], np.float32).reshape(-1, 3)
    opacity0 = np.array(params["background.opacities"], np.float32).ravel()
    centres = read_ply(os.path.join(args.fit, "background.ply")).centers
    if len(centres) != len(normal0):
        raise SystemExit("%s: background.ply has %d Gaussians, the loaded scene %d"
                         % (args.fit, len(centres), len(normal0)))
    points, point_normals = truth_surface(gt, frames, positions)
    pick, dist = nearest_points(points, centres)
    true_n = point_normals[pick]
    true_n = true_n * np.sign(np.sum(true_n * normal0, axis=1, keepdims=True) + 1e-12)
    on = dist <= args.off
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(normal0 * true_n, axis=1)), 0.0, 1.0)))
    print("%s: %d background Gaussians, %.3f within %.2f m of a true surface (opacity-weighted %.3f); "
          "their normals %.1f deg from the surface's (median %.1f)"
          % (args.fit, len(centres), on.mean(), args.off, np.sum(opacity0 * on) / np.sum(opacity0),
             ang[on].mean(), np.median(ang[on])))

    variants = {"fit": (normal0, opacity0),
                "true normals": (np.where(on[:, None], true_n, normal0), opacity0),
                "on-surface only": (normal0, np.where(on, opacity0, 0.0)),
                "both": (np.where(on[:, None], true_n, normal0), np.where(on, opacity0, 0.0))}
    print("Each column: mean error there [deg], its share of the mean [deg]; 'other depth': "
          "pixels whose fitted depth is more than %d %% from the truth's" % round(100 * SAME_DEPTH))
    print("| variant | mean [deg] | at the truth's edges | tree crowns off the edges | the rest "
          "| other depth (share of pixels) | other depth, edges |")
    print("|---|---|---|---|---|---|---|")
    pictures = {}
    for name, (normal, opacity) in variants.items():
        params["background.normal"] = mi.Float(np.ascontiguousarray(normal, np.float32).ravel())
        params["background.opacities"] = mi.Float(np.ascontiguousarray(opacity, np.float32))
        params.update()
        a, e, c, same, pictures[name] = normal_error(scene, frames, positions, gt, args.spp)
        c = c & ~e
        parts = ["%.1f, %.2f" % (a[s].mean(), a[s].sum() / len(a)) if s.any() else "-"
                 for s in (e, c, ~e & ~c, ~same, ~same & e)]
        parts[3] += " (%.3f)" % np.mean(~same)
        print("| %s | %.2f | %s |" % (name, a.mean(), " | ".join(parts)), flush=True)
    if args.write:
        for name, (normal, opacity) in variants.items():
            if name != "fit":
                print("wrote %s" % write_variant(args.fit, name, normal, opacity))
    if args.png:
        draw({k: pictures[k] for k in ("fit", "both")}, args.png)
        print("wrote %s (fit, then both)" % args.png)


if __name__ == "__main__":
    main()
