"""Render benchmark: ``invrgbl`` (camera) and ``lidar_return`` (LiDAR) vs raw traversal.

Run from the repository root::

    python tests/bench/bench_render.py [--sizes 10000,100000,1000000] [--quick]

Prints one table. Per scene size (a seeded street: a ground layer, building-like
facades and end walls of flat Gaussians, and random blobs) and task:

* camera fwd / fwd+bwd: ``invrgbl`` at 256x256, spp 1, with its per-Gaussian
  lighting cache already filled (the stage-2 situation: geometry frozen);
* camera light precompute: the extra cost of the first render after the
  geometry or lights changed (sky + sun visibility traced per Gaussian), i.e.
  median(render with an emptied cache) - median(cached render); its rays and
  hits are the visibility (shadow) rays;
* lidar fwd / fwd+bwd: ``lidar_return`` with the ``lidar`` sensor, 64x1024.

Backward: grad enabled on the Gaussians' ``albedo``, ``lidar_albedo``,
``opacities`` (+ ``data`` for the LiDAR), ``mi.render(scene, params)`` then
``dr.backward(dr.sum(img))``.

Wall time is the median of ``--runs`` runs after one warm-up run (its time is
reported as "1st run"; it includes JIT compilation, which Dr.Jit may partly
serve from its on-disk kernel cache). ``raw`` is a symbolic loop of
``scene.ray_intersect_preliminary`` over the same rays that only steps past each
hit until a miss or the same ``max_hits`` cap (no transmittance cut-off, no
shading), measured in the same process; ``x raw`` = time / raw time, shown
against the project's targets (forward <= 1.5x, forward+backward <= 3x).

Memory: the process's peak RSS (``VmHWM``) cannot be reset between rows, so the
table shows the peak after the row and how much the row raised it
(0 = the row stayed below an earlier peak).
"""

from __future__ import annotations

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse
import math
import statistics
import sys
import time

import numpy as np
import drjit as dr
import mitsuba as mi

CAMERA_RES = 256
LIDAR_W, LIDAR_H = 1024, 64
FWD_TARGET, BWD_TARGET = 1.5, 3.0


def _setup_variant():
    import mi_invrgbl  # noqa: F401  (registers the plugins)


# ---------------------------------------------------------------- memory
def peak_rss_mb():
    """Peak resident set size of this process (MB)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# ----------------------------------------------------------------- scene
def street_cloud(n, seed=0):
    """A street of ``n`` Gaussians: ground, facades, end walls and blobs (numpy).

    Flat Gaussians are sized so that about ``OVERLAP`` of them cover any point of
    their surface whatever ``n`` is, so rays see a similar number of hits at
    every scene size.
    """
    rng = np.random.default_rng(seed)
    overlap = 14.0
    L, W, H = 40.0, 8.0, 12.0           # half length, half width, wall height
    n_blob = int(0.12 * n)
    n_ground = int(0.45 * n)
    n_wall = n - n_blob - n_ground
    # Surfaces: (area, sampler) -> centres + axis of the thin dimension.
    walls = [  # (kind, fixed coord, range1, range2)
        ("y", -W, (-L, L), (0, H)), ("y", W, (-L, L), (0, H)),
        ("x", -L, (-W, W), (0, H)), ("x", L, (-W, W), (0, H)),
    ]
    areas = np.array([(r1[1] - r1[0]) * (r2[1] - r2[0]) for _, _, r1, r2 in walls])
    counts = np.floor(n_wall * areas / areas.sum()).astype(int)
    counts[0] += n_wall - counts.sum()

    centers, scales, normals = [], [], []

    def flat(count, area, axis, pos):
        density = count / area
        sigma = math.sqrt(overlap / (math.pi * 9.0 * density))  # 3-sigma support
        s = np.empty((count, 3), np.float32)
        s[:] = sigma * rng.uniform(0.7, 1.3, (count, 1))
        s[:, axis] = 0.02 * rng.uniform(0.5, 1.5, count)
        nrm = np.zeros((count, 3), np.float32)
        nrm[:, axis] = 1.0
        centers.append(pos.astype(np.float32))
        scales.append(s)
        normals.append(nrm)

    g = np.stack([rng.uniform(-L, L, n_ground), rng.uniform(-W, W, n_ground),
                  rng.normal(0, 0.01, n_ground)], 1)
    flat(n_ground, 2 * L * 2 * W, 2, g)
    for (kind, c, r1, r2), cnt in zip(walls, counts):
        a = rng.uniform(*r1, cnt)
        b = rng.uniform(*r2, cnt)
        off = rng.normal(0, 0.01, cnt) + c
        if kind == "y":
            pos, axis = np.stack([a, off, b], 1), 1
        else:
            pos, axis = np.stack([off, a, b], 1), 0
        flat(cnt, (r1[1] - r1[0]) * (r2[1] - r2[0]), axis, pos)
    # Blobs: parked-car / tree-like clusters in the street volume.
    n_clusters = 40
    cc = np.stack([rng.uniform(-L, L, n_clusters), rng.uniform(-W + 1, W - 1, n_clusters),
                   rng.uniform(0.3, 3.0, n_clusters)], 1)
    which = rng.integers(0, n_clusters, n_blob)
    pos = cc[which] + rng.normal(0, 0.8, (n_blob, 3))
    pos[:, 2] = np.abs(pos[:, 2])
    blob_sigma = 0.8 * (n_clusters * 4.0 / max(n_blob, 1)) ** (1 / 3) * 1.2
    s = (blob_sigma * rng.uniform(0.5, 1.5, (n_blob, 3))).astype(np.float32)
    centers.append(pos.astype(np.float32))
    scales.append(s)
    normals.append(np.zeros((n_blob, 3), np.float32))  # -> shortest axis

    centers = np.concatenate(centers)
    scales = np.concatenate(scales)
    normals = np.concatenate(normals)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    flat_n = n - n_blob
    q[:flat_n] = (1, 0, 0, 0)  # flat Gaussians stay axis-aligned (w x y z)
    # Blobs: normal = shortest axis, computed here so the tensor is complete.
    from mi_invrgbl.physics.gaussian_ply import quaternion_to_matrix
    r = quaternion_to_matrix(q[flat_n:].astype(np.float64))
    k = np.argmin(scales[flat_n:], axis=1)
    normals[flat_n:] = r[np.arange(n_blob), :, k]
    return dict(
        centers=centers, scales=scales, quaternions=q,
        opacities=rng.uniform(0.6, 0.95, n).astype(np.float32),
        normals=normals,
        albedo=rng.uniform(0.1, 0.8, (n, 3)).astype(np.float32),
        roughness=rng.uniform(0.2, 0.9, n).astype(np.float32),
        lidar_albedo=rng.uniform(0.05, 0.6, n).astype(np.float32),
    )


def build_scene(n, seed, samples, max_hits):
    cloud = street_cloud(n, seed)
    gauss = {"type": "gaussians", "id": "street"}
    for k, v in cloud.items():
        gauss[k] = mi.TensorXf(v)
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "street": gauss,
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.7, 0.9]}},
        "sun": {"type": "directional", "direction": [-0.3, -0.2, -0.93],
                "irradiance": {"type": "rgb", "value": [3.0, 2.9, 2.7]}},
        "camera": {
            "type": "perspective", "fov": 70,
            "to_world": T().look_at(origin=[-30, 1.0, 1.7], target=[40, 0, 1.2], up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": CAMERA_RES, "height": CAMERA_RES,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 1},
        },
        "lidar": {
            "type": "lidar", "to_world": T().translate([0, 0.5, 1.7]),
            "film": {"type": "hdrfilm", "width": LIDAR_W, "height": LIDAR_H,
                     "rfilter": {"type": "box"}},
        },
    })
    cam_int = mi.load_dict({"type": "invrgbl", "samples": samples, "max_hits": max_hits})
    lidar_int = mi.load_dict({"type": "lidar_return", "max_hits": max_hits})
    return scene, cam_int, lidar_int


# ------------------------------------------------------------ traversal
@dr.syntax
def raw_traverse(scene, rays, max_hits):
    """Hits per ray of a bare ``ray_intersect_preliminary`` loop (no shading)."""
    o = mi.Point3f(rays.o)
    d = mi.Vector3f(rays.d)
    maxt = mi.Float(rays.maxt)
    t_offset = mi.Float(0)
    count = mi.UInt32(0)
    active = mi.Bool(True)
    while active:
        pi = scene.ray_intersect_preliminary(mi.Ray3f(o, d, maxt - t_offset), False, active)
        hit = active & pi.is_valid()
        step = pi.t + 1e-5 + 1e-6 * (pi.t + t_offset)  # same step as hits.trace
        o[hit] = o + d * step
        t_offset[hit] += step
        count[hit] += 1
        active = hit & (count < max_hits)
    return count


def camera_rays(scene, integrator):
    sensor = scene.sensors()[0]
    with dr.suspend_grad():
        sampler, _ = integrator.prepare(sensor, 0, 1, integrator.aov_names())
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
        rays = mi.Ray3f(dr.detach(ray))
        dr.eval(rays)
    return rays


def lidar_rays(scene, integrator):
    rays, _, _, _ = integrator.beam_rays(scene.sensors()[1])
    dr.eval(rays)
    return rays


def shadow_rays(scene, integrator):
    """The visibility rays of ``invrgbl``'s lighting precompute and their cap."""
    from mi_invrgbl.physics import hits as hitlib
    from mi_invrgbl.physics import lighting as L
    nodes = hitlib.gaussian_nodes(scene)
    with dr.suspend_grad():
        # As GaussianLighting does, without filling (i.e. tracing) a cache.
        table = L.GaussianTable.build(nodes).load_geometry()
        G, M = table.total, integrator.samples
        per = dr.arange(mi.UInt32, G * M) // M
        frames = mi.Frame3f(dr.gather(mi.Vector3f, table.normal, per))
        dirs = frames.to_world(L.fibonacci_hemisphere(M, L._hash_rotation(G)))
        origins = dr.gather(mi.Point3f, table.center, per)
        sky = mi.Ray3f(origins, dirs)
        dr.eval(sky)
        out = [sky]
        for kind, emitter in L.point_lights(scene):
            d, _, _ = L.light_at(kind, emitter, table.center)
            out.append(mi.Ray3f(table.center, d))
    return out, L.SHADOW_MAX_HITS


def fill_lighting_cache(scene, integrator):
    """Fill ``invrgbl``'s lighting cache with visibility 1 without tracing it."""
    from mi_invrgbl.physics import hits as hitlib
    from mi_invrgbl.physics import lighting as L
    nodes = hitlib.gaussian_nodes(scene)
    lights = L.point_lights(scene)
    G = sum(node.count for node in nodes)
    trace_sun = integrator.sun_visibility == "trace"
    sky_key, light_key = L.cache_keys(scene, nodes, lights, integrator.samples,
                                      integrator.bounces, 0, trace_sun)
    cache = integrator.cache
    cache.sky_visibility = dr.ones(mi.Float, G * integrator.samples)
    cache.light_visibility = [dr.ones(mi.Float, G) for _ in lights]
    dr.eval(cache.sky_visibility, cache.light_visibility)
    cache.key, cache.light_key = sky_key, light_key


def count_hits(scene, rays, max_hits, min_transmittance=1e-3):
    from mi_invrgbl.physics import hits as hitlib
    h = hitlib.trace(scene, rays, max_hits, min_transmittance)
    return int(dr.sum(h.count)[0])


# --------------------------------------------------------------- timing
def timed(fn, runs):
    """(first run, median of ``runs`` later runs, peak RSS after, its increase)."""
    before = peak_rss_mb()
    t0 = time.perf_counter()
    fn()
    dr.sync_thread()
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    after = peak_rss_mb()
    return first, statistics.median(times), after, after - before


def grad_params(scene, lidar):
    params = mi.traverse(scene)
    keys = ["street.albedo", "street.lidar_albedo", "street.opacities"]
    if lidar:
        keys.append("street.data")
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    return params, keys


def clear_grads(params, keys):
    for k in keys:
        dr.disable_grad(params[k])
    params.update()


def run_size(n, args, rows):
    t0 = time.perf_counter()
    rss0 = peak_rss_mb()
    scene, cam, lid = build_scene(n, args.seed, args.samples, args.max_hits)
    build = time.perf_counter() - t0
    print("# %d Gaussians: scene build %.2f s (peak RSS +%.0f MB)" %
          (n, build, peak_rss_mb() - rss0), file=sys.stderr, flush=True)
    K = args.max_hits

    def add(task, res, n_rays, n_hits, raw, target):
        first, med, peak, dpeak = res
        rows.append(dict(n=n, task=task, first=first, t=med, rays=n_rays, hits=n_hits,
                         peak=peak, dpeak=dpeak, raw=raw, target=target))
        print("#   %-22s %8.3f s (1st %.2f s)  x raw %s" %
              (task, med, first, "%.2f" % (med / raw) if raw else "-"),
              file=sys.stderr, flush=True)

    # ---- camera
    crays = camera_rays(scene, cam)
    n_cam = dr.width(crays.o)
    chits = count_hits(scene, crays, K)
    raw_cam = timed(lambda: dr.eval(raw_traverse(scene, crays, K)), args.runs)[1]
    raw_cam_hits = int(dr.sum(raw_traverse(scene, crays, K))[0])

    def cam_fwd():
        dr.eval(mi.render(scene, sensor=0, integrator=cam, spp=1))

    def cam_cold():
        cam.cache.key = ()
        cam_fwd()

    precompute = n <= args.precompute_max
    if precompute:
        cold = timed(cam_cold, args.runs)       # also compiles the lighting kernels
    else:
        fill_lighting_cache(scene, cam)
    fwd = timed(cam_fwd, args.runs)
    add("camera fwd", fwd, n_cam, chits, raw_cam, FWD_TARGET)

    params, keys = grad_params(scene, lidar=False)

    def cam_bwd():
        img = mi.render(scene, params, sensor=0, integrator=cam, spp=1)
        dr.backward(dr.sum(img))
        dr.eval([dr.grad(params[k]) for k in keys])
        for k in keys:
            dr.clear_grad(params[k])

    add("camera fwd+bwd", timed(cam_bwd, args.runs), n_cam, chits, raw_cam, BWD_TARGET)
    clear_grads(params, keys)

    # Lighting precompute: its shadow rays, hits and raw traversal.
    raw_sh = None
    if precompute:
        srays, s_cap = shadow_rays(scene, cam)
        n_sh = sum(dr.width(r.o) for r in srays)
        sh_hits = sum(count_hits(scene, r, s_cap) for r in srays)
        raw_sh = timed(lambda: dr.eval([raw_traverse(scene, r, s_cap) for r in srays]),
                       args.runs)[1]
        pre = (cold[0] - fwd[1], cold[1] - fwd[1], cold[2], cold[3])
        add("camera light precompute", pre, n_sh, sh_hits, raw_sh, FWD_TARGET)
        rows[-1]["cold"] = cold
        del srays
    else:
        from mi_invrgbl.physics.lighting import SHADOW_MAX_HITS as s_cap, point_lights
        n_sh = n * (args.samples + len(point_lights(scene)))
        rows.append(dict(n=n, info="camera light precompute: skipped above --precompute-max "
                                   "%d (%d shadow rays, cap %d); the cache was filled with "
                                   "visibility 1 (per-frame cost does not depend on its values)"
                                   % (args.precompute_max, n_sh, s_cap)))

    # ---- LiDAR
    lrays = lidar_rays(scene, lid)
    n_lid = dr.width(lrays.o)
    lhits = count_hits(scene, lrays, K)
    raw_lid = timed(lambda: dr.eval(raw_traverse(scene, lrays, K)), args.runs)[1]
    raw_lid_hits = int(dr.sum(raw_traverse(scene, lrays, K))[0])

    def lid_fwd():
        dr.eval(mi.render(scene, sensor=1, integrator=lid))

    add("lidar fwd", timed(lid_fwd, args.runs), n_lid, lhits, raw_lid, FWD_TARGET)
    params, keys = grad_params(scene, lidar=True)

    def lid_bwd():
        img = mi.render(scene, params, sensor=1, integrator=lid)
        dr.backward(dr.sum(img))
        dr.eval([dr.grad(params[k]) for k in keys])
        for k in keys:
            dr.clear_grad(params[k])

    add("lidar fwd+bwd", timed(lid_bwd, args.runs), n_lid, lhits, raw_lid, BWD_TARGET)
    clear_grads(params, keys)
    info = ("raw traversal: camera %.3f s (%.1f hits/ray, cap %d), lidar %.3f s "
            "(%.1f hits/ray)" % (raw_cam, raw_cam_hits / n_cam, K, raw_lid, raw_lid_hits / n_lid))
    if raw_sh is not None:
        info += ", shadow rays %.3f s; first-ever camera render (compile + precompute + " \
                "frame) %.2f s, cold-cache render %.3f s" % (raw_sh, cold[0], cold[1])
    rows.append(dict(n=n, info=info + "; scene build %.2f s" % build))
    del scene, cam, lid, params


def print_table(rows, args):
    head = ("%-9s %-24s %9s %9s %9s %9s %8s %9s %9s %7s %6s %-10s" %
            ("gaussians", "task", "time [s]", "1st [s]", "rays/s", "hits/s", "hits/ray",
             "peak MB", "+peak MB", "x raw", "target", "verdict"))
    print()
    print("invrgbl %dx%d spp 1 (samples M=%d), lidar_return %dx%d; max_hits %d; "
          "median of %d runs after a warm-up" %
          (CAMERA_RES, CAMERA_RES, args.samples, LIDAR_H, LIDAR_W, args.max_hits, args.runs))
    print(head)
    print("-" * len(head))
    for r in rows:
        if "info" in r:
            print("%-9s   %s" % ("", r["info"]))
            continue
        ratio = r["t"] / r["raw"] if r["raw"] else float("nan")
        verdict = "PASS" if ratio <= r["target"] else "MISS"
        print("%-9d %-24s %9.3f %9.2f %9.3g %9.3g %8.1f %9.0f %9.0f %7.2f %6s %-10s" %
              (r["n"], r["task"], r["t"], r["first"], r["rays"] / r["t"], r["hits"] / r["t"],
               r["hits"] / r["rays"], r["peak"], r["dpeak"], ratio,
               "<=%.1f" % r["target"], verdict))
    print()
    print("1st = the warm-up run (JIT compile + run; the camera kernels compile in the "
          "precompute row's warm-up: first-ever render - cached render). hits counted from the hit lists (transmittance "
          "cut-off 1e-3); raw traversal runs to a miss or the cap. Peak RSS (VmHWM) "
          "cannot be reset: '+peak' is how much the row raised the process peak.")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--quick", action="store_true", help="10k Gaussians only")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--samples", type=int, default=16, help="invrgbl sky samples M")
    ap.add_argument("--max-hits", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--precompute-max", type=int, default=200000,
                    help="time the lighting precompute only up to this many Gaussians")
    args = ap.parse_args(argv)
    _setup_variant()
    sizes = [10000] if args.quick else [int(s) for s in args.sizes.split(",") if s]
    rows = []
    for n in sizes:
        run_size(n, args, rows)
    print_table(rows, args)
    return rows


if __name__ == "__main__":
    main()
