"""Fit benchmark: per-iteration time of stage 1 and stage 2 against a full re-trace.

Run from the repository root::

    python tests/bench/bench_fit.py [--cases 96,320] [--large] [--runs 5] [--quick]

(about 3 minutes on 2 cores; ``--large`` adds ``320@100000``, about 5 more;
``--quick`` is the 96 case alone, about 1 minute).

Prints one markdown table. A *case* ``WIDTH[@GAUSSIANS]`` is the street of
``tests/fit_scene.py`` (5 frames, 4 training + 1 held out; camera WIDTH x
WIDTH/3 pixels, LiDAR 64 x ``--lidar-columns`` beams), its truth rendered and
written as observations; ``@GAUSSIANS`` first densifies the bundled PLY to
that many Gaussians (each split into children spread over its support with
proportionally smaller in-plane scales, so a ray sees about as many
Gaussians as before). Every case runs in its own process, so its peak RSS is
its own. Per case the rows are:

* **stage 1**: ``Stage1.iteration`` (pull, push = BVH update, trace + blend of
  a random batch of ``--batch`` camera pixels and as many LiDAR beams,
  backward, Adam step, clamping, gradient accumulation for densification);
  densification itself (every 50 iterations) is not included;
* **stage 2**: ``Stage2.iteration`` on a full training frame (camera + LiDAR)
  with the cached hit lists and cached visibility (``FrozenScene``): shading,
  all stage-2 losses, backward, Adam step;
* **full re-trace** (the reference): the very same ``Stage2.iteration`` after
  re-tracing that frame's camera and LiDAR hit lists (``render.freeze``) and
  replacing its ``LightingCache`` with an empty one, so the per-Gaussian sky
  and sun visibility is traced again, as it must be whenever geometry moves.
  The BVH rebuild that a geometry change also needs is *not* included (it is
  reported separately), so the reference is the cheapest uncached iteration;
* **hits re-traced**: the same with only the hit lists re-traced (visibility
  kept);
* **plugin re-render**: a cross-check through the plugins' own path:
  ``mi.render`` of the frame's camera with ``invrgbl`` (spp 1, the fit's
  ``samples``/``max_hits``/``min_transmittance``, an emptied lighting cache)
  and ``lidar_return.render_beams`` of its beams, with the material, sky and
  sun parameters grad-enabled, ``dr.backward`` of the image + intensity sums
  (no losses, no optimiser step).

``traced/it`` counts the rays that went through ``hits.trace`` per iteration
(0 proves that stage 2 traces nothing). A stage-2 or hits-only run that
traced more than the row's other runs (a ``LightingCache`` invalidated under
it, e.g. when the optimised sun irradiance reaches 0 and the sun leaves
``point_lights``) is left out of the median when such runs are a minority,
and reported in the note column. ``÷ full`` is the row's time over the
full re-trace; ``s2 ÷ row`` is stage 2's time over the row's, checked against
the target (stage 2 <= 0.1 x a re-trace iteration).

Timing: every iteration ends with the optimiser's variables evaluated and
``dr.sync_thread()``; the first (compiling) iterations are warm-up and not
timed (their time is shown as "1st"); the time is the median of ``--runs``
iterations. Stage 2 warms up once on every training frame (this also builds
each frame's SLIC superpixels), and its timed runs visit the frames in turn,
as do the reference rows, so all stage-2-like rows do the same work.

Memory: peak RSS (``VmHWM``) cannot be reset, so each row shows the process
peak after it and how much it raised it; the hit-list cache is
``FrozenScene.nbytes()`` and the lighting cache is its visibility arrays.

The machine's load average is printed with the table: on a shared machine
absolute times move with it; the ratios are taken within one process, a few
seconds apart, and move less.
"""

from __future__ import annotations

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
TARGET = 0.1


def _setup():
    import mitsuba as mi
    import mi_invrgbl  # noqa: F401  (registers the plugins)
    tests = os.path.join(ROOT, "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)


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


def parse_case(spec):
    spec = spec.strip()
    width, _, count = spec.partition("@")
    return int(width), int(float(count)) if count else 0


# --------------------------------------------------------------- scene
def densify_cloud(cloud, target, seed=0):
    """``cloud`` split into about ``target`` Gaussians covering the same support."""
    from mi_invrgbl.physics.gaussian_ply import GaussianCloud, quaternion_to_matrix
    n = len(cloud.centers)
    if target <= n:
        return cloud
    rng = np.random.default_rng(seed)
    k = target // n
    children = np.full(n, k, np.int64)
    children[rng.choice(n, target - k * n, replace=False)] += 1
    parent = np.repeat(np.arange(n), children)
    per = children[parent].astype(np.float64)
    s = cloud.scales[parent].astype(np.float64)
    # Spread children over the parent's two largest axes (its surface); the
    # thinnest axis keeps its size, the others shrink so the area is kept.
    thin = np.argmin(s, axis=1)
    plane = np.ones_like(s, bool)
    plane[np.arange(len(s)), thin] = False
    z = rng.normal(size=s.shape) * plane
    rot = quaternion_to_matrix(cloud.quaternions[parent].astype(np.float64))
    offset = np.einsum("nij,nj->ni", rot, s * z * np.sqrt(1.0 - 1.0 / per)[:, None])
    s_new = np.where(plane, s / np.sqrt(per)[:, None], s)
    pick = lambda a: None if a is None else a[parent].copy()  # noqa: E731
    return GaussianCloud(centers=(cloud.centers[parent] + offset).astype(np.float32),
                         scales=s_new.astype(np.float32), quaternions=pick(cloud.quaternions),
                         opacities=pick(cloud.opacities), normals=pick(cloud.normals),
                         albedo=pick(cloud.albedo), roughness=pick(cloud.roughness),
                         lidar_albedo=pick(cloud.lidar_albedo),
                         sun_visibility=pick(cloud.sun_visibility), source="densified")


def build_case(workdir, width, gaussians, columns, seed):
    """Write the fit scene of a case; returns (scene path, Gaussian count)."""
    import fit_scene
    from mi_invrgbl.physics.gaussian_ply import read_ply, write_ply
    height = max(8, int(round(width / 3)))
    base = fit_scene.PLY
    count = len(read_ply(base).centers)
    try:
        if gaussians and gaussians > count:
            dense = densify_cloud(read_ply(base), gaussians, seed)
            path = os.path.join(workdir, "densified_source.ply")
            write_ply(path, dense)
            fit_scene.PLY = path
            count = len(dense.centers)
        scene = fit_scene.build(workdir, n_frames=5, width=width, height=height, columns=columns)
    finally:
        fit_scene.PLY = base
    return scene, count


# -------------------------------------------------------------- tracing
class TraceCounter:
    """Counts the rays that go through ``hits.trace`` (all tracing goes there)."""

    def __init__(self):
        from mi_invrgbl.physics import hits
        self.module, self.original = hits, hits.trace
        self.rays = 0
        self.calls = 0

        def counted(scene, rays, *a, **kw):
            import drjit as dr
            self.rays += dr.width(rays.o)
            self.calls += 1
            return self.original(scene, rays, *a, **kw)

        hits.trace = counted

    def reset(self):
        self.rays, self.calls = 0, 0

    def close(self):
        self.module.trace = self.original


# --------------------------------------------------------------- timing
def timed(step, warmup, runs, counter):
    """(first warm-up iteration's time, per-run times, per-run traced rays).

    ``step(k)`` runs the k-th iteration and returns what must be evaluated
    (the optimiser's variables), so that nothing is left pending.
    """
    import drjit as dr
    first = None
    for k in range(warmup):
        t0 = time.perf_counter()
        dr.eval(step(k))
        dr.sync_thread()
        if first is None:
            first = time.perf_counter() - t0
    times, traced = [], []
    for k in range(warmup, warmup + runs):
        counter.reset()
        t0 = time.perf_counter()
        dr.eval(step(k))
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
        traced.append(counter.rays)
    return first, times, traced


def summarise(res, drop_extra_traces):
    """Median time and traced rays; with ``drop_extra_traces``, runs that traced
    more than the row's minimum (a cache was invalidated under it) are left
    out of the median when they are a minority, and counted."""
    first, times, traced = res
    keep = list(range(len(times)))
    extra = [i for i in keep if traced[i] > min(traced)]
    if drop_extra_traces and extra and 2 * len(extra) < len(times):
        keep = [i for i in keep if i not in extra]
    return dict(first=first, t=statistics.median([times[i] for i in keep]),
                traced=statistics.median([traced[i] for i in keep]), times=times,
                traced_runs=traced, extra=[i for i in extra])


def opt_values(opt):
    return [opt[k] for k in opt.keys()]


def run_case(spec, args):
    """Measure one case; returns its rows (dicts)."""
    _setup()
    import drjit as dr
    import mitsuba as mi
    from mi_invrgbl.fit.progress import SpeedErrorLog
    from mi_invrgbl.fit.render import freeze
    from mi_invrgbl.fit.init import init_materials, load_state
    from mi_invrgbl.fit.model_selection import choose_lighting
    from mi_invrgbl.fit.runner import FitConfig, apply_lighting
    from mi_invrgbl.fit.stage1 import Stage1
    from mi_invrgbl.fit.stage2 import FrozenScene, Stage2
    from mi_invrgbl.physics.lighting import LightingCache

    width, gaussians = parse_case(spec)
    workdir = tempfile.mkdtemp(prefix="bench_fit_", dir=args.workdir)
    rows, info = [], {}
    say = lambda *a: print("#", *a, file=sys.stderr, flush=True)  # noqa: E731
    try:
        t = time.perf_counter()
        scene_path, count = build_case(workdir, width, gaussians, args.lidar_columns, args.seed)
        info["build_s"] = time.perf_counter() - t
        cfg = FitConfig(output=os.path.join(workdir, "fit"), fit_width=width,
                        lidar_columns=args.lidar_columns, batch_rays=args.batch,
                        lidar_batch_rays=args.batch,
                        max_hits=args.max_hits, samples=args.samples, sun=args.sun,
                        seed=args.seed, checkpoint_every=0)
        ctx = load_state(scene_path, cfg, log=lambda *a: None)
        ctx.speed_log = SpeedErrorLog(os.path.join(cfg.output, "log.csv"))
        cam0 = ctx.train_frames[0].camera
        lid0 = ctx.train_frames[0].lidar
        label = "%dx%d px, %d G" % (cam0.width, cam0.height, ctx.model.total)
        load0 = os.getloadavg()[0]
        info.update(case=spec, label=label, frames=len(ctx.observations), gaussians=ctx.model.total, pixels=cam0.width * cam0.height,
                    beams=dr.width(lid0.rays.o), train_frames=len(ctx.train_frames))
        say("case %s: %s, %d LiDAR beams, %d training frames; scene built in %.1f s"
            % (spec, label, info["beams"], info["train_frames"], info["build_s"]))
        counter = TraceCounter()

        def add(name, res, drop_extra_traces=False, **extra):
            r = summarise(res, drop_extra_traces)
            rows.append(dict(case=spec, label=label, row=name, peak=peak_rss_mb(), **r, **extra))
            say("  %-16s %8.4f s/it (1st %.2f s; runs %s; traced %s)"
                % (name, r["t"], r["first"], " ".join("%.3f" % x for x in r["times"]),
                   " ".join("%d" % x for x in r["traced_runs"])))

        rss = peak_rss_mb()
        # ------------------------------------------------------------ stage 1
        s1 = Stage1(ctx)
        n_s1 = min(args.batch, info["pixels"]) + min(args.batch, info["beams"])

        def stage1_step(k):
            s1.iteration(k + 1)
            return opt_values(s1.opt.adam)

        add("stage 1", timed(stage1_step, args.warmup, args.runs, counter),
            rays=n_s1, dpeak=peak_rss_mb() - rss)
        s1.pull()
        ctx.model.push(ctx.train_frames[0].poses, stage=1)
        t = time.perf_counter()
        apply_lighting(ctx, choose_lighting(ctx))
        info["selection_s"] = time.perf_counter() - t

        # ------------------------------------------------- freeze + stage 2
        rss = peak_rss_mb()
        counter.reset()
        t = time.perf_counter()
        frozen = FrozenScene(ctx, ctx.observations)
        dr.sync_thread()
        info["freeze_s"] = time.perf_counter() - t
        info["freeze_rays"] = counter.rays
        info["hit_cache_mb"] = frozen.nbytes() / 2**20
        info["freeze_dpeak"] = peak_rss_mb() - rss
        hits = [frozen.camera[f.index].hit_count for f in ctx.train_frames if f.index in frozen.camera]
        lhits = [frozen.lidar[f.index].hit_count for f in ctx.train_frames if f.index in frozen.lidar]
        info["hits_per_pixel"] = float(np.mean(hits)) / info["pixels"] if hits else 0.0
        info["hits_per_beam"] = float(np.mean(lhits)) / info["beams"] if lhits else 0.0
        init_materials(ctx, frozen)
        s2 = Stage2(ctx, frozen)
        frames = list(ctx.train_frames)
        n_s2 = info["pixels"] + info["beams"]

        def on_frame(k, body):
            # Stage2.iteration draws its frame from ctx.train_frames: pin it so
            # every stage-2-like row visits the same frames in the same order.
            frame = frames[k % len(frames)]
            ctx.train_frames = [frame]
            try:
                body(frame)
                s2.iteration(k + 1)
            finally:
                ctx.train_frames = frames
            return opt_values(s2.opt.adam)

        rss = peak_rss_mb()
        add("stage 2", timed(lambda k: on_frame(k, lambda f: None), len(frames), args.runs, counter),
            drop_extra_traces=True, rays=n_s2, dpeak=peak_rss_mb() - rss)
        n_vis = len(frozen.caches[frames[0].index].light_visibility)
        G = ctx.model.total
        info["vis_rays"] = G * (cfg.samples + n_vis)
        info["lights"] = n_vis
        cache = frozen.caches[frames[0].index]
        info["light_cache_mb"] = 4 * (dr.width(cache.sky_visibility) + sum(
            dr.width(v) for v in cache.light_visibility if v is not None)) / 2**20

        # --------------------------------------------------- re-trace refs
        saved_hits = (dict(frozen.camera), dict(frozen.lidar))
        saved_caches = dict(frozen.caches)

        def retrace_hits(frame):
            if frame.camera is not None:
                frozen.camera[frame.index] = freeze(ctx.scene, frame.camera.rays, cfg.max_hits,
                                                    cfg.min_transmittance)
            if frame.lidar is not None:
                frozen.lidar[frame.index] = freeze(ctx.scene, frame.lidar.rays, cfg.max_hits,
                                                   cfg.min_transmittance)

        def retrace_all(frame):
            retrace_hits(frame)
            frozen.caches[frame.index] = LightingCache()

        ref_runs = args.ref_runs or args.runs
        rss = peak_rss_mb()
        add("full re-trace", timed(lambda k: on_frame(k, retrace_all), 1, ref_runs, counter),
            rays=n_s2, dpeak=peak_rss_mb() - rss)
        frozen.caches.clear()
        frozen.caches.update(saved_caches)
        rss = peak_rss_mb()
        add("hits re-traced", timed(lambda k: on_frame(k, retrace_hits), 1, ref_runs, counter),
            drop_extra_traces=True, rays=n_s2, dpeak=peak_rss_mb() - rss)
        frozen.camera.clear(); frozen.camera.update(saved_hits[0])  # noqa: E702
        frozen.lidar.clear(); frozen.lidar.update(saved_hits[1])  # noqa: E702

        # ----------------------------------------------- plugin re-render
        s2.commit()
        ctx.model.push(frames[0].poses, stage=2)
        cam_int = mi.load_dict({"type": "invrgbl", "samples": cfg.samples, "max_hits": cfg.max_hits,
                                "min_transmittance": cfg.min_transmittance})
        params = ctx.params
        keys = [n + "." + k for n in ctx.model.nodes for k in ("albedo", "roughness", "lidar_albedo",
                                                               "normal")]
        keys += [ctx.sky_key] + ([ctx.sun_key] if ctx.use_sun else [])
        for k in keys:
            dr.enable_grad(params[k])
        params.update()

        def plugin_step(k):
            frame = frames[k % len(frames)]
            cam_int.cache = LightingCache()
            loss = mi.Float(0.0)
            if frame.camera is not None:
                img = mi.render(ctx.scene, params, sensor=frame.camera.sensor, integrator=cam_int,
                                spp=1, seed=k)
                loss += dr.mean(img, axis=None)
            if frame.lidar is not None:
                lid = frame.lidar
                ch = ctx.lidar_integrator.render_beams(ctx.scene, lid.rays, lid.row, near=lid.near)
                loss += dr.mean(ch[0], axis=None)
            dr.backward(loss)
            grads = [dr.grad(params[k]) for k in keys]
            for key in keys:
                dr.clear_grad(params[key])
            return grads

        rss = peak_rss_mb()
        add("plugin re-render", timed(plugin_step, 1, ref_runs, counter), rays=n_s2,
            dpeak=peak_rss_mb() - rss)
        for k in keys:
            dr.disable_grad(params[k])
        params.update()

        # ------------------------------------------- BVH rebuild alone
        def push_step(k):
            ctx.model.push(frames[k % len(frames)].poses, stage=2)
            return []

        info["bvh_s"] = statistics.median(timed(push_step, 1, args.runs, counter)[1])
        counter.close()
        info["sun_end"] = "(%s)" % ", ".join(
            "%.3g" % float(x) for x in np.array(dr.detach(params[ctx.sun_key])).ravel())
        info["load"] = (load0, os.getloadavg()[0])
        info["peak_mb"] = peak_rss_mb()
        rows.append(dict(case=spec, info=info))
        say("  done: peak RSS %.0f MB" % info["peak_mb"])
        return rows
    finally:
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            say("  kept %s" % workdir)


# ----------------------------------------------------------------- table
REFERENCES = ("full re-trace", "hits re-traced", "plugin re-render")


def print_table(rows, args):
    loads = [r["info"]["load"] for r in rows if "info" in r]
    print()
    print("Fit per-iteration time: tests/fit_scene.py street, LiDAR 64x%d beams, stage-1 batch %d "
          "camera + %d LiDAR rays, M=%d sky samples, max_hits %d; median of %d runs (%d for the "
          "re-trace rows) after warm-up; %d CPU(s), load average during the cases %s"
          % (args.lidar_columns, args.batch, args.batch, args.samples, args.max_hits, args.runs,
             args.ref_runs or args.runs, os.cpu_count() or 0,
             ", ".join("%.1f-%.1f" % tuple(x) for x in loads)))
    print()
    print("| case | row | rays/it | traced/it | time/it [s] | 1st [s] | ÷ full | s2 ÷ row | "
          "target | verdict | peak RSS [MB] | +peak [MB] | note |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---|")
    by_case = {}
    for r in rows:
        by_case.setdefault(r["case"], []).append(r)
    for case, rs in by_case.items():
        named = {r["row"]: r for r in rs if "row" in r}
        full = named.get("full re-trace", {}).get("t")
        s2 = named.get("stage 2", {}).get("t")
        for r in rs:
            if "row" not in r:
                continue
            ratio = s2 / r["t"] if r["row"] in REFERENCES and s2 else None
            note = ""
            if r["extra"]:
                n, k = len(r["times"]), len(r["extra"])
                note = "%d/%d run(s) traced more (%s rays)%s" % (
                    k, n, "/".join("%d" % r["traced_runs"][i] for i in r["extra"]),
                    ", left out" if 2 * k < n and r["row"] in ("stage 2", "hits re-traced") else "")
            print("| %s | %s | %d | %.0f | %.4f | %.2f | %s | %s | %s | %s | %.0f | %.0f | %s |" % (
                r["label"], r["row"], r["rays"], r["traced"], r["t"], r["first"],
                "%.3f" % (r["t"] / full) if full else "-",
                "%.3f" % ratio if ratio is not None else "",
                "<= %.1f" % TARGET if ratio is not None else "",
                ("PASS" if ratio <= TARGET else "MISS") if ratio is not None else "",
                r["peak"], r["dpeak"], note))
    print()
    for case, rs in by_case.items():
        for r in rs:
            if "info" not in r:
                continue
            i = r["info"]
            print("- %s: %d training frames of %d pixels + %d beams, %.1f hits/pixel, %.1f hits/beam; "
                  "hit-list cache (FrozenScene.nbytes, all %d frames) %.1f MB; lighting cache %.1f MB "
                  "(%d visibility rays = G x (M + %d light(s))); freeze %.2f s (%d rays, +%.0f MB "
                  "peak); stage 2's first iteration also fills the lighting cache; BVH rebuild alone "
                  "(model.push) %.4f s; lighting selection %.1f s; scene build %.1f s; sun irradiance "
                  "after the stage-2 rows %s; process peak RSS %.0f MB"
                  % (i["label"], i["train_frames"], i["pixels"], i["beams"], i["hits_per_pixel"],
                     i["hits_per_beam"], i["frames"], i["hit_cache_mb"], i["light_cache_mb"],
                     i["vis_rays"], i["lights"], i["freeze_s"], i["freeze_rays"], i["freeze_dpeak"],
                     i["bvh_s"], i["selection_s"], i["build_s"], i["sun_end"], i["peak_mb"]))
    print()
    print("÷ full: the row's time / the full re-trace's. s2 ÷ row: stage 2's time / the row's, "
          "target: stage 2 <= %.1f x a re-trace iteration. traced/it: rays through hits.trace per "
          "timed iteration (stage 2 must trace none). 1st: the first warm-up iteration (JIT "
          "compilation, partly served from Dr.Jit's kernel cache; for stage 2 also the lighting "
          "cache fill). Peak RSS (VmHWM) cannot be reset: '+peak' is how much the row raised the "
          "process peak; each case runs in its own process." % TARGET)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="96,320",
                    help="comma-separated WIDTH[@GAUSSIANS]: camera width, and the street "
                         "densified to GAUSSIANS (default: 96,320)")
    ap.add_argument("--large", action="store_true", help="add the case 320@100000 (~5 more minutes)")
    ap.add_argument("--quick", action="store_true", help="the 96-pixel case only")
    ap.add_argument("--runs", type=int, default=5, help="timed iterations per row")
    ap.add_argument("--ref-runs", type=int, default=3, help="timed iterations of the re-trace rows")
    ap.add_argument("--warmup", type=int, default=2, help="stage-1 warm-up iterations")
    ap.add_argument("--batch", type=int, default=4096, help="stage-1 camera rays and as many LiDAR beams per step")
    ap.add_argument("--lidar-columns", type=int, default=512)
    ap.add_argument("--samples", type=int, default=16, help="sky samples M per Gaussian")
    ap.add_argument("--max-hits", type=int, default=24)
    ap.add_argument("--sun", default="on", choices=("on", "off", "auto"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--in-process", action="store_true", help="run every case in this process")
    ap.add_argument("--workdir", default=None, help="where the case scenes are written (temporary)")
    ap.add_argument("--keep", action="store_true", help="keep the case scenes")
    ap.add_argument("--one-case", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--json", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.one_case:
        rows = run_case(args.one_case, args)
        with open(args.json, "w") as f:
            json.dump(rows, f)
        return rows

    cases = ["96"] if args.quick else [c for c in args.cases.split(",") if c.strip()]
    if args.large and not args.quick:
        cases.append("320@100000")
    rows = []
    for case in cases:
        if args.in_process:
            rows += run_case(case, args)
            continue
        fd, out = tempfile.mkstemp(suffix=".json")
        os.close(fd)
        try:
            forward = ["--runs", str(args.runs), "--ref-runs", str(args.ref_runs),
                       "--warmup", str(args.warmup), "--batch", str(args.batch),
                       "--lidar-columns", str(args.lidar_columns), "--samples", str(args.samples),
                       "--max-hits", str(args.max_hits), "--sun", args.sun, "--seed", str(args.seed)]
            forward += ["--workdir", args.workdir] if args.workdir else []
            forward += ["--keep"] if args.keep else []
            cmd = [sys.executable, os.path.abspath(__file__), *forward, "--one-case", case,
                   "--json", out]
            subprocess.run(cmd, check=True, cwd=ROOT)
            with open(out) as f:
                rows += json.load(f)
        finally:
            os.remove(out)
    print_table(rows, args)
    return rows


if __name__ == "__main__":
    main()
