"""``mi-invrgbl import``: a recorded (or synthetic) drive -> an editable scene.

Reads a KITTI raw drive or a KITTI odometry layout (the synthetic street),
and writes the layout of ``docs/scene_format.md``: ``scene.xml``,
``frames.json``, ``background.ply``, ``object_<track>.ply`` and
``observations/``. Steps (each timed):

read
    The drive (:mod:`mi_invrgbl.io.kitti`), the selected frames' sweeps and
    images (downscaled with ``image_scale``, intrinsics scaled to match).
    A frame whose sweep is empty is skipped with a warning; sweeps with
    NaN/inf points lose those points with a warning (both in
    :mod:`mi_invrgbl.io.velodyne`).
odometry
    Given poses (GPS/IMU ``oxts`` or ``poses/XX.txt``) are used whenever
    present; otherwise KISS-ICP LiDAR odometry. ``check_odometry`` runs
    odometry on a drive that has poses and reports the trajectory error.
    The world frame is the first imported frame's LiDAR frame.
accumulate
    Every sweep in the world frame; its range image (``azimuth_steps`` wide,
    rows = beams) for ``observations/lidar_NNNN.exr``. Of the training
    sweeps only (a held-out frame's sweep is an observation for ``eval``,
    nothing more), points inside a dynamic object's box (in the frames it
    is labelled or interpolated) go to the object, in its own frame; the
    rest within [``min_range``, ``max_range``] to the background.
extend walls
    A LiDAR sees nothing above its top beam, so the upper part of a facade
    that a camera sees would have no Gaussians at all. Vertical structures
    (an xy cell of ``0.25`` m whose points span >= 1 m in height) whose top
    point was measured by the top beams (elevation within 0.6 degrees of the
    highest beam, i.e. cut by the field of view, not a real top edge) are
    extended upward by ``extend_walls`` metres in 0.25 m steps; the new
    points inherit their seed's intensity and range, and are exempt from the
    random thinning to ``max_points`` (up to 40 % of it) so that extended
    walls stay opaque enough to cast shadows. Stage 1 of ``fit`` lowers the
    opacity of those that the images show as sky.
normals
    Background: voxel dedupe (``voxel``), random subsample to ``max_points``
    (seeded), k-NN (OpenCV FLANN); normal by local PCA over the
    ``normal_knn`` nearest voxels before the subsample (over the ``knn``
    nearest kept Gaussians with ``normal_knn`` 0), oriented towards the
    sensors that saw the voxel; a Gaussian on a wall extension takes the
    normal of the measured point it extends, made horizontal. Tangent frame
    from the kept Gaussians' neighbours, scales from their spacing (tangent
    0.5 x mean k-NN distance, normal 0.1 x that), LiDAR
    albedo from intensity corrected for range and incidence angle
    (:func:`mi_invrgbl.io.init_gaussians.lidar_albedo`).
objects
    Per dynamic object ``object_points`` Gaussians in its box (object frame):
    its LiDAR points when there are enough, topped up with samples on the
    box's sides and top. An object whose scan the top beam cut (a truck
    beside the car) gets its cut columns continued ``object_headroom``
    metres up (:func:`mi_invrgbl.io.objects.extend_object_top`), on top of
    the ``object_points``.
colours
    Albedo from the training images: each Gaussian's centre (objects at
    their per-frame pose) projected into every training frame, z-buffered
    against all centres, averaged in linear RGB (weights 1/depth); never
    seen -> 0.5. No held-out image or sweep gives a Gaussian its place,
    colour or LiDAR albedo (every sweep still enters the poses: the
    odometry and the moving objects' tracks, as labels would).
write
    Everything into a temporary sibling folder, a ``mi.load_file`` check of
    the scene, then one rename: a folder under the output name is complete.

The steps hand on one :class:`ImportState`, each filling its own fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
from pathlib import Path
import shutil
import time
import warnings

import numpy as np

from .. import outdir
from ..errors import UserError
from . import init_gaussians as ig
from .images import read_image_uint8
from .triangulate import held_out
from .objects import (tracks_to_objects, in_box, box_surface_samples, extend_object_top,
                      OBJECT_HEADROOM, TOP_BEAM_MARGIN_DEG)

#: sweeps with fewer points are skipped (with a warning)
MIN_SCAN_POINTS = 10


@dataclass
class ImportOptions:
    frames: str | None = None          # "A:B[:S]" slice of the drive's frames
    max_points: int = 800_000
    voxel: float = 0.05                # metres
    azimuth_steps: int = 1024
    image_scale: float = 1.0
    seed: int = 0
    dynamic: str = "moving"            # moving | all | none
    knn: int = 10
    normal_knn: int = 16               # voxels whose PCA gives a Gaussian's normal (0: its knn centres)
    opacity: float = 0.7
    roughness: float = 0.5
    min_range: float = 1.0             # metres; background accumulation only
    max_range: float = 80.0
    object_points: int = 5000
    check_odometry: bool = False
    intensity: str = "auto"            # auto | raw | reflectivity
    reference_range: float | None = None   # raw intensity: range at which white reads 1
    beams: int | None = None
    sky_order: int = 2
    sun_irradiance: float = 0.0
    extend_walls: float = 10.0         # metres above the top beam's hits (0: off)
    object_headroom: float = OBJECT_HEADROOM  # metres above a cut object's top (0: off)
    triangulate: bool = True           # camera-only geometry (io/triangulate.py)
    motion: bool = True                # moving objects from the LiDAR when unlabelled (io/motion.py)
    follow_nodes: bool = False         # follow those nodes past their tracks (motion.follow_node)
    overwrite: bool = False
    verify: bool = True

    def validate(self) -> "ImportOptions":
        if self.max_points < 100:
            raise UserError(f"--max-points must be at least 100 (got {self.max_points})")
        if not self.voxel > 0:
            raise UserError(f"--voxel must be > 0 (got {self.voxel})")
        if self.azimuth_steps < 8:
            raise UserError(f"--azimuth-steps must be at least 8 (got {self.azimuth_steps})")
        if not 0 < self.image_scale <= 1:
            raise UserError(f"--image-scale must lie in (0, 1] (got {self.image_scale})")
        if self.dynamic not in ("moving", "all", "none"):
            raise UserError(f"--dynamic must be moving, all or none (got {self.dynamic})")
        if self.intensity not in ("auto", "raw", "reflectivity"):
            raise UserError(f"--intensity must be auto, raw or reflectivity (got {self.intensity})")
        if not 0 < self.opacity < 1:
            raise UserError(f"--opacity must lie in (0, 1) (got {self.opacity})")
        if not 0.02 <= self.roughness <= 1:
            raise UserError(f"--roughness must lie in [0.02, 1] (got {self.roughness})")
        if self.knn < 3:
            raise UserError(f"--knn must be at least 3 (got {self.knn})")
        if self.normal_knn != 0 and self.normal_knn < 3:
            raise UserError(f"--normal-knn must be 0 or at least 3 (got {self.normal_knn})")
        if self.object_points < 10:
            raise UserError(f"--object-points must be at least 10 (got {self.object_points})")
        if not 0 <= self.min_range < self.max_range:
            raise UserError("--min-range must be >= 0 and below --max-range")
        if not 0 <= self.extend_walls <= 100:
            raise UserError(f"--extend-walls must lie in [0, 100] metres (got {self.extend_walls})")
        if not 0 <= self.object_headroom <= 10:
            raise UserError(f"--object-headroom must lie in [0, 10] metres (got {self.object_headroom})")
        if self.sky_order not in (0, 1, 2, 3):
            raise UserError(f"--sky-order must be 0..3 (got {self.sky_order})")
        return self


@dataclass
class ImportReport:
    out_dir: Path
    scene: Path
    times: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    odometry: dict = field(default_factory=dict)
    objects: list = field(default_factory=list)   # per track: decision summary


@dataclass
class BackgroundPoints:
    """Every sweep's background points in the world frame, one row per point."""
    points: np.ndarray             # (N, 3) float32, world frame
    intensity: np.ndarray          # (N,) the sensor's intensity
    range: np.ndarray              # (N,) metres from the sensor that saw the point
    frame: np.ndarray              # (N,) position of that sweep among the imported frames
    #: (N,) int64: for a point added above a wall cut by the top beam, the
    #: measured point it extends (its normal is that point's); -1 for measured points.
    seed: np.ndarray | None = None

    @property
    def extended(self) -> np.ndarray | None:
        """(N,) bool: added above a wall cut by the top beam."""
        return None if self.seed is None else self.seed >= 0


@dataclass
class ImportState:
    """What the steps hand on, filled step by step (see the module docstring)."""
    # read
    positions: list                # drive positions of the imported frames
    scans: list                    # per frame: (points (N, 3), intensity (N,)), sensor frame
    images: list                   # per frame: (H, W, 3) uint8 RGB at the output size
    K: np.ndarray                  # 3x3 intrinsics at the output size
    size: tuple                    # (W, H) of the output images
    crop: tuple | None             # source crop (W, H) before downscaling, None if none
    skipped: list                  # source frame numbers skipped (empty sweeps)
    counts: dict = field(default_factory=dict)          # reported numbers, by name
    odometry: dict = field(default_factory=dict)        # odometry timing and errors
    object_report: list = field(default_factory=list)   # per track: the decision taken
    # odometry
    poses: np.ndarray | None = None        # (F, 4, 4) world_from_lidar
    pose_source: str = ""                  # where the poses came from
    cam_poses: np.ndarray | None = None    # (F, 4, 4) world_from_camera (dataset frame)
    objects: list = field(default_factory=list)         # ObjectTrack per labelled track
    # accumulate
    intensity: tuple = ("raw", None)       # (kind, reference range) of the LiDAR intensity
    lidar_table: np.ndarray | None = None  # beam elevations (radians), top first
    lidar_rays: np.ndarray | None = None   # (N, 7) explicit ray pattern (origin, direction, beam)
    beams: int = 0
    range_images: list = field(default_factory=list)    # per frame: the observed range image
    world_points: list = field(default_factory=list)    # per frame: (N, 4) x y z intensity
    bg: BackgroundPoints | None = None
    # normals
    background: dict | None = None         # the background's Gaussian fields, by name
    # objects
    object_clouds: dict = field(default_factory=dict)   # object name -> its Gaussian fields
    # motion (unlabelled drives): moving LiDAR points, tracks and masks (io/motion.py)
    motion: object | None = None


class _Steps:
    def __init__(self, log):
        self.log = log
        self.times = {}

    def run(self, name, fn, *args, **kwargs):
        t = time.perf_counter()
        out = fn(*args, **kwargs)
        dt = time.perf_counter() - t
        self.times[name] = self.times.get(name, 0.0) + dt
        self.log("[import] %-12s %7.2f s" % (name, dt))
        return out


# ----------------------------------------------------------------------------
# Source detection
# ----------------------------------------------------------------------------

@dataclass
class Source:
    drive: object                  # kitti.Drive
    kind: str                      # 'raw' or 'odometry'
    labels: Path | None
    gt_dir: Path | None
    synthetic: dict | None         # gt/trajectory.json when present


def open_source(data) -> Source:
    """Detect the layout of ``data`` and read it (no sweeps or images yet)."""
    from . import kitti

    path = Path(data)
    if not path.exists():
        raise UserError(f"{path}: input folder not found")
    if not path.is_dir():
        raise UserError(f"{path}: not a folder (expected a KITTI raw drive or a KITTI "
                        "odometry root with sequences/)")
    is_odometry = ((path / "sequences").is_dir() or (path / "calib.txt").is_file()
                   or (path / "velodyne").is_dir())
    if is_odometry:
        drive = kitti.read_kitti_odometry(path)
        root = drive.root.parent.parent
        labels = root / "label_02" / ("%04d.txt" % int(drive.root.name)) \
            if drive.root.name.isdigit() else None
        if labels is not None and not labels.is_file():
            labels = None
        gt = root / "gt"
        synthetic = None
        if (gt / "trajectory.json").is_file():
            try:
                synthetic = json.loads((gt / "trajectory.json").read_text())
            except json.JSONDecodeError as exc:
                raise UserError(f"{gt / 'trajectory.json'}: not valid JSON ({exc})") from None
        return Source(drive, "odometry", labels, gt if gt.is_dir() else None, synthetic)
    drive = kitti.read_kitti_raw(path)
    return Source(drive, "raw", None, None, None)


def _parse_slice(text: str | None, n: int, what="--frames") -> list:
    if not text:
        return list(range(n))
    try:
        parts = [int(p) if p.strip() else None for p in text.split(":")]
        if len(parts) == 1:
            sl = slice(parts[0], parts[0] + 1)
        elif len(parts) in (2, 3):
            sl = slice(*parts)
        else:
            raise ValueError
    except ValueError:
        raise UserError(f"{what} '{text}': expected A:B or A:B:STEP (frame positions)") from None
    picked = list(range(n))[sl]
    if not picked:
        raise UserError(f"{what} '{text}' selects no frame of the {n} available")
    return picked


def _scaled_size(W0, H0, scale):
    """Output size and the source crop (from the top left, so the principal
    point stays put) that make the downscale the same along x and y: Mitsuba's
    camera has square pixels. E.g. 1242x375 at 0.25 -> crop 1240x372 -> 310x93."""
    if scale == 1:
        return W0, H0, (W0, H0)
    W, H = max(1, int(W0 * scale)), max(1, int(H0 * scale))
    Wc, Hc = W / scale, H / scale
    if abs(Wc - round(Wc)) < 1e-6 and abs(Hc - round(Hc)) < 1e-6:
        return W, H, (int(round(Wc)), int(round(Hc)))
    return W, H, (W0, H0)        # no exact crop: scales differ by < 1 pixel over the image


# ----------------------------------------------------------------------------
# The import
# ----------------------------------------------------------------------------

def _out_paths(out_xml):
    out_xml = Path(out_xml).absolute()
    if out_xml.suffix.lower() != ".xml":
        raise UserError(f"{out_xml}: the output must be a scene file DIR/scene.xml")
    return out_xml, out_xml.parent


def import_scene(data, out_xml, options: ImportOptions | None = None, log=print) -> ImportReport:
    """Run the whole import (see the module docstring); returns the report."""
    opts = (options or ImportOptions()).validate()
    out_xml, out_dir = _out_paths(out_xml)
    # Checked (and a temporary folder made) before any work: see mi_invrgbl.outdir.
    out = outdir.prepare(out_dir, "import", inputs=[data], overwrite=opts.overwrite)
    steps = _Steps(log)
    t_total = time.perf_counter()
    try:
        src, state = steps.run("read", _read, data, opts, log)
        steps.run("odometry", _odometry, src, state, opts, log)
        if opts.motion and src.labels is None and opts.dynamic != "none":
            from .motion import import_step as motion_step
            steps.run("motion", motion_step, src, state, opts, log)
        steps.run("accumulate", _accumulate, src, state, opts, log)
        if opts.extend_walls > 0:
            steps.run("extend walls", _extend_walls, state, opts, log)
        steps.run("normals", _background, state, opts, log)
        if opts.triangulate:
            from .triangulate import import_step
            steps.run("triangulate", import_step, src, state, opts, log)
        steps.run("objects", _objects, state, opts, log)
        steps.run("colours", _colours, state, opts, log)
        frames = steps.run("write", _write, src, state, opts, out.path, out_xml.name, data)
        if state.motion is not None:
            steps.run("motion masks", _write_motion_masks, state, frames, out.path)
        if opts.verify:
            steps.run("verify", _verify, out.path / out_xml.name)
        out.commit()
    except BaseException:
        out.discard()
        raise
    steps.times["total"] = time.perf_counter() - t_total
    report = ImportReport(out_dir, out_xml, steps.times, state.counts, state.odometry,
                          state.object_report)
    report.counts["frames"] = len(frames)
    return report


# -- read ----------------------------------------------------------------------

def _read(data, opts, log):
    src = open_source(data)
    drive = src.drive
    positions = _parse_slice(opts.frames, len(drive))
    W0, H0 = drive.image_size
    W, H, crop = _scaled_size(W0, H0, opts.image_scale)
    sx, sy = W / crop[0], H / crop[1]
    K = drive.K.copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    if abs(K[0, 0] - K[1, 1]) > 5e-3 * K[0, 0]:
        warnings.warn(f"{drive.calib_files[0]}: fx = {K[0, 0]:.2f} and fy = {K[1, 1]:.2f} "
                      "differ; Mitsuba's perspective camera has square pixels, fy is ignored",
                      UserWarning, stacklevel=2)
    kept, scans, images, skipped = [], [], [], []
    for p in positions:
        pts, inten = drive.load_scan(p)
        if pts.shape[0] < MIN_SCAN_POINTS:
            warnings.warn(f"{drive.scan_paths[p]}: {pts.shape[0]} LiDAR points; frame "
                          f"{drive.frames[p]} skipped", UserWarning, stacklevel=2)
            skipped.append(int(drive.frames[p]))
            continue
        kept.append(p)
        scans.append((pts, inten))
        images.append(read_image_uint8(drive.image_paths[p], (W, H), crop, (W0, H0)))
    if not kept:
        raise UserError(f"{drive.root}: no frame with a usable LiDAR sweep")
    log("[import] %s (%s layout): %d frames%s, image %dx%d -> %dx%d"
        % (drive.root, src.kind, len(kept),
           " (%d skipped)" % len(skipped) if skipped else "", W0, H0, W, H))
    state = ImportState(positions=kept, scans=scans, images=images, K=K, size=(W, H),
                        crop=crop if tuple(crop) != (W0, H0) else None, skipped=skipped,
                        counts={"skipped_frames": len(skipped)})
    return src, state


# -- odometry --------------------------------------------------------------------

def _odometry(src, state: ImportState, opts, log):
    from . import odometry

    drive = src.drive
    kept = state.positions
    if drive.poses is not None:
        P = drive.poses[kept]
        poses = np.linalg.inv(P[0]) @ P
        source = drive.pose_source
        if opts.check_odometry:
            t = time.perf_counter()
            full = odometry.lidar_odometry([s[0] for s in state.scans])
            state.odometry["kiss_icp_s"] = time.perf_counter() - t
            err = odometry.trajectory_error(full, poses)
            t = time.perf_counter()
            est_ng = odometry.lidar_odometry([odometry.remove_ground(s[0])
                                              for s in state.scans])
            err_ng = odometry.trajectory_error(est_ng, poses)
            state.odometry.update({
                "ate_m": err.ate_m, "drift_percent": err.drift_percent,
                "final_rotation_deg": err.final_rotation_deg,
                "path_length_m": err.path_length_m,
                "ate_m_ground_removed": err_ng.ate_m,
                "drift_percent_ground_removed": err_ng.drift_percent,
                "final_rotation_deg_ground_removed": err_ng.final_rotation_deg,
                "kiss_icp_ground_removed_s": time.perf_counter() - t})
            log("[import] odometry check vs %s: %s" % (source, err))
            log("[import] odometry check, ground points dropped: %s" % err_ng)
    else:
        t = time.perf_counter()
        times = drive.timestamps[kept] if drive.timestamps is not None else None
        poses, checked = odometry.checked_odometry(
            [s[0] for s in state.scans], timestamps=times, images=state.images,
            K=state.K, T_velo_to_cam=drive.T_velo_to_cam2, source=str(drive.root))
        state.odometry["kiss_icp_s"] = time.perf_counter() - t
        state.odometry.update(checked.summary())
        source = "odometry"
        log("[import] poses by LiDAR odometry (ground removed): %.1f m travelled over %d frames"
            "%s" % (checked.length_m, len(poses),
                    "" if checked.full_sweep_length_m is None else
                    " (full sweeps: %.1f m)" % checked.full_sweep_length_m))
        for c in checked.checks:
            log("[import] odometry check, %s: %s (%s)" % (c.name, "agrees" if c.agrees
                                                        else "DISAGREES", c.detail))
    state.odometry["trajectory_length_m"] = odometry.path_length(poses)
    state.poses = poses
    state.pose_source = source
    T_velo_to_cam2 = drive.T_velo_to_cam2
    state.cam_poses = poses @ np.linalg.inv(T_velo_to_cam2)
    # Objects from tracking labels (world = first imported LiDAR frame).
    objects = []
    if src.labels is not None:
        from . import kitti
        world_from_cam0 = {int(drive.frames[p]): poses[k] @ np.linalg.inv(drive.T_velo_to_cam)
                           for k, p in enumerate(kept)}
        # Labels of frames outside the import are irrelevant: keep them readable.
        all_frames = dict(world_from_cam0)
        for f in drive.frames:
            all_frames.setdefault(int(f), np.eye(4))
        tracks = kitti.read_tracking_labels(src.labels, world_from_cam=_LenientPoses(all_frames))
        objects = tracks_to_objects(tracks, [int(drive.frames[p]) for p in kept], opts.dynamic)
    state.objects = objects
    for o in objects:
        decision = "dynamic node" if o.dynamic else "background"
        log("[import] track %d (%s): moves %.2f m over its labels -> %s -> %s"
            % (o.track_id, o.kind, o.displacement_m, "moving" if o.moving else "static",
               decision))
        state.object_report.append({"track_id": o.track_id, "kind": o.kind,
                                       "displacement_m": o.displacement_m,
                                       "moving": o.moving, "dynamic": o.dynamic,
                                       "labelled_frames": int(o.labelled.sum())})


class _LenientPoses(dict):
    """A frame -> pose dict that also answers for frames outside the drive
    (labels of frames that were not imported are read but never used)."""

    def __contains__(self, key):
        return True

    def __missing__(self, key):
        return np.eye(4)


# -- accumulate ----------------------------------------------------------------------

def _lidar_table(state, opts, log):
    """Beam count and table from the sweeps themselves (any spinning sensor,
    any point order); ``None`` for the table when KITTI's firing order
    assigns the beams sweep by sweep. An explicit ray pattern is kept in
    ``state.lidar_rays`` (the ``lidar`` sensor's ``rays`` mode)."""
    from .range_image import detect_beam_layout
    layout = detect_beam_layout([pts for pts, _ in state.scans], n_beams=opts.beams)
    log("[import] LiDAR: %s" % layout.describe())
    if layout.kind == "rays":
        state.lidar_rays = np.column_stack([np.zeros((len(layout.rays), 3)), layout.rays,
                                            layout.ray_beam]).astype(np.float64)
    if layout.method == "scan_order":
        return layout.n_beams, None
    return layout.n_beams, layout.elevations


def _intensity_kind(src, opts):
    if opts.intensity != "auto":
        kind = opts.intensity
    elif src.synthetic is not None:
        kind = ((src.synthetic or {}).get("lidar") or {}).get("intensity", "raw")
    else:
        kind = "reflectivity"      # KITTI's HDL-64 (raw and odometry layouts)
    ref = opts.reference_range
    if ref is None:
        ref = 2.0
        li = (src.synthetic or {}).get("lidar") or {}
        if "intensity_scale" in li:
            ref = float(np.sqrt(float(li["intensity_scale"]) * float(li.get("power", 1.0)) / np.pi))
    return kind, ref


def _accumulate(src, state: ImportState, opts, log):
    from .range_image import range_image, ray_image

    beams, table = _lidar_table(state, opts, log)
    state.intensity = _intensity_kind(src, opts)
    W = opts.azimuth_steps
    poses = state.poses
    dyn = [o for o in state.objects if o.dynamic]
    bg_pts, bg_int, bg_rng, bg_frame = [], [], [], []
    rimgs, methods, tables, world_points = [], [], [], []
    for i, (pts, inten) in enumerate(state.scans):
        t = poses[i][:3, 3]
        world = ig.transform_points(pts, poses[i])
        world_points.append(np.hstack([world, inten[:, None]]).astype(np.float32))
        if state.lidar_rays is not None:
            ri = ray_image(pts, inten, state.lidar_rays[:, 3:6], table)
        else:
            ri = range_image(pts, inten, width=W, n_beams=beams, beam_elevations=table)
        rimgs.append(ri)
        methods.append(ri.method)
        tables.append(ri.elevations)
        if held_out(i):
            # A held-out sweep is written as an observation for `eval` and
            # nothing more: were its points Gaussians (and its intensities
            # their LiDAR albedo), `eval` would score the fit on points it
            # was built from, against a nearest-neighbour baseline that only
            # has the training sweeps.
            continue
        rng = np.linalg.norm(pts.astype(np.float64), axis=1)
        keep = (rng >= opts.min_range) & (rng <= opts.max_range)
        for o in dyn:
            if not o.active(i):
                continue
            inv = np.linalg.inv(o.poses[i])
            p_obj = ig.transform_points(world, inv)
            inside = in_box(p_obj, o.half_extent) & (rng >= opts.min_range)
            if inside.any():
                q = pts[inside].astype(np.float64)
                o.elevation.append(np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1])))
                sensor_obj = inv[:3, :3] @ t + inv[:3, 3]
                view = sensor_obj - p_obj[inside]
                o.points.append(p_obj[inside])
                o.intensity.append(inten[inside])
                o.distance.append(rng[inside])
                o.view.append(view / np.linalg.norm(view, axis=1, keepdims=True))
            keep &= ~inside
        bg_pts.append(world[keep].astype(np.float32))
        bg_int.append(inten[keep])
        bg_rng.append(rng[keep].astype(np.float32))
        bg_frame.append(np.full(int(keep.sum()), i, np.int32))

    if table is None:
        good = [e for e, m in zip(tables, methods) if m == "scan_order"]
        table = np.median(np.stack(good if good else tables), axis=0)
        redo = [i for i, m in enumerate(methods) if m != "scan_order"]
        for i in redo:
            pts, inten = state.scans[i]
            rimgs[i] = range_image(pts, inten, width=W, n_beams=beams, beam_elevations=table)
        if redo:
            log("[import] %d of %d sweeps lost their firing order; beams assigned by "
                "elevation with the drive's median beam table" % (len(redo), len(tables)))
    state.lidar_table = np.asarray(table)
    state.beams = beams
    state.range_images = rimgs
    state.world_points = world_points
    state.bg = BackgroundPoints(np.concatenate(bg_pts), np.concatenate(bg_int),
                                np.concatenate(bg_rng), np.concatenate(bg_frame))
    n_acc = len(state.bg.points)
    state.counts["points_accumulated"] = n_acc
    state.counts["points_total"] = int(sum(len(w) for w in world_points))
    for o in dyn:
        state.counts["points_" + o.name] = int(sum(len(p) for p in o.points))
    log("[import] %d background points from %d training sweeps (%d in all %d sweeps; %d in "
        "moving objects)" % (n_acc, sum(not held_out(i) for i in range(len(world_points))),
                             state.counts["points_total"], len(world_points),
                             sum(sum(len(p) for p in o.points) for o in dyn)))


# -- wall extension ---------------------------------------------------------------------

def _extend_walls(state: ImportState, opts, log, cell=0.25, min_height=1.0, step=0.25, margin_deg=0.6):
    bg = state.bg
    P = bg.points.astype(np.float64)
    poses = state.poses
    if P.shape[0] == 0:
        return
    # Elevation of each point in its own sweep's sensor frame.
    R = poses[bg.frame, :3, :3]
    t = poses[bg.frame, :3, 3]
    local = np.einsum("nji,nj->ni", R, P - t)
    elev = np.arctan2(local[:, 2], np.hypot(local[:, 0], local[:, 1]))
    top_beam = float(np.max(state.lidar_table))
    cut = elev >= top_beam - np.radians(margin_deg)
    keys = np.floor(P[:, :2] / cell).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    ncell = int(inv.max()) + 1
    zmax = np.full(ncell, -np.inf)
    zmin = np.full(ncell, np.inf)
    np.maximum.at(zmax, inv, P[:, 2])
    np.minimum.at(zmin, inv, P[:, 2])
    tall = (zmax - zmin) >= min_height
    # Seed: the highest top-beam point of each tall cell, if it is the cell's top.
    cand = np.nonzero(cut & tall[inv] & (P[:, 2] >= zmax[inv] - 0.2))[0]
    if cand.size == 0:
        state.counts["wall_extension_points"] = 0
        log("[import] no facade cut by the LiDAR's top beam: nothing to extend")
        return
    order = cand[np.argsort(-P[cand, 2])]
    _, first = np.unique(inv[order], return_index=True)
    seeds = order[first]
    k = np.arange(1, int(opts.extend_walls / step) + 1)
    n_new = seeds.size * k.size
    new = np.repeat(P[seeds], k.size, axis=0)
    new[:, 2] += np.tile(k * step, seeds.size)
    for key, values in (("points", new.astype(np.float32)),
                        ("intensity", np.repeat(bg.intensity[seeds], k.size)),
                        ("range", np.repeat(bg.range[seeds], k.size)),
                        ("frame", np.repeat(bg.frame[seeds], k.size))):
        old = getattr(bg, key)
        setattr(bg, key, np.concatenate([old, values.astype(old.dtype)]))
    bg.seed = np.concatenate([np.full(len(P), -1, np.int64), np.repeat(seeds, k.size)])
    state.counts["wall_extension_points"] = int(n_new)
    log("[import] %d facade columns cut by the top beam extended by %.1f m (%d points)"
        % (seeds.size, opts.extend_walls, n_new))


# -- background Gaussians ---------------------------------------------------------------

def _background(state: ImportState, opts, log):
    bg = state.bg
    P = bg.points
    if P.shape[0] < opts.knn + 1:
        raise UserError(f"only {P.shape[0]} LiDAR points within {opts.min_range}-"
                        f"{opts.max_range} m of the sensor: nothing to build a scene from")
    kind, ref = state.intensity
    origins = state.poses[:, :3, 3][bg.frame]
    view = origins - P.astype(np.float64)
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-9)

    first, inverse = ig.voxel_dedupe(P, opts.voxel)
    nvox = first.size
    rng = np.random.default_rng(opts.seed)
    if nvox > opts.max_points:
        # Measured points are dense (many sweeps, 5 cm voxels) and are thinned
        # at random; wall extensions are already on a coarse grid, so thinning
        # them alike would leave see-through walls (and no cast shadows).
        # They are kept whole, up to 40 % of the budget.
        ext = bg.extended
        ext_vox = ext[first] if ext is not None else np.zeros(nvox, bool)
        ext_ids, real_ids = np.nonzero(ext_vox)[0], np.nonzero(~ext_vox)[0]
        cap = int(0.4 * opts.max_points)
        if ext_ids.size > cap:
            ext_ids = rng.choice(ext_ids, cap, replace=False)
        n_real = min(real_ids.size, opts.max_points - ext_ids.size)
        sel = np.sort(np.concatenate([ext_ids, rng.choice(real_ids, n_real, replace=False)]))
    else:
        sel = np.arange(nvox)
    slot = np.full(nvox, -1, np.int64)
    slot[sel] = np.arange(sel.size)
    pslot = slot[inverse]                         # per point: its Gaussian or -1
    used = pslot >= 0
    n = sel.size
    # Every voxel's mean point: the kept ones are the Gaussians' centres,
    # and all of them give the normals (below).
    dense = ig.group_mean(P, inverse, nvox)
    centres = dense[sel]
    vmean = ig.group_mean(view[used], pslot[used], n)

    idx, dist = ig.knn(centres, opts.knn)
    k = opts.normal_knn or opts.knn
    if opts.normal_knn > 0:
        # Frames from every voxel, not from the thinned centres: kept at
        # random, the centres' neighbours span a metre or more and reach
        # round corners and across tree crowns.
        normals, tangents, _ = ig.pca_frames(dense, ig.knn(dense, k, queries=sel)[0])
    else:
        normals, tangents, _ = ig.pca_frames(centres, idx)
    # A Gaussian added above a wall cut by the top beam stands on a column
    # of made-up points whose PCA says nothing about the wall: it takes the
    # normal of the measured point it extends, made horizontal (the
    # extension is vertical).
    seed = bg.seed[first[sel]] if bg.seed is not None else np.full(n, -1)
    ext = np.nonzero(seed >= 0)[0]
    if ext.size:
        n_seed, _, _ = ig.pca_frames(dense, ig.knn(dense, k, queries=inverse[seed[ext]])[0])
        n_seed[:, 2] = 0.0
        length = np.linalg.norm(n_seed, axis=1)
        wall = length > 0.2        # a seed whose normal is near vertical keeps the PCA one
        normals[ext[wall]] = n_seed[wall] / length[wall, None]
    normals = ig.orient_towards(normals, vmean)
    quats = ig.frames_to_quaternions(tangents, normals)
    scales = ig.tangent_scales(dist, smallest=0.2 * opts.voxel, largest=0.5)

    cos = np.abs(np.sum(normals[pslot[used]] * view[used], axis=1))
    rho_pt = ig.lidar_albedo(bg.intensity[used], bg.range[used], cos, kind, ref)
    rho = ig.group_mean(rho_pt, pslot[used], n)

    state.background = {"centers": centres.astype(np.float32), "scales": scales,
                           "quaternions": quats.astype(np.float32),
                           "normals": normals.astype(np.float32),
                           "lidar_albedo": rho.astype(np.float32)}
    state.counts.update({"voxels": int(nvox), "background_gaussians": int(n)})
    log("[import] %d voxels of %.3f m -> %d background Gaussians (max %d); LiDAR "
        "intensity '%s'%s" % (nvox, opts.voxel, n, opts.max_points, kind,
                             " (white at %.2f m reads 1)" % ref if kind == "raw" else ""))



# -- objects ----------------------------------------------------------------------------

def _objects(state: ImportState, opts, log):
    kind, ref = state.intensity
    rng = np.random.default_rng([opts.seed, 1])
    clouds = {}
    for o in state.objects:
        if not o.dynamic:
            continue
        m = opts.object_points
        if o.points:
            P = np.concatenate(o.points)
            inten = np.concatenate(o.intensity)
            dist = np.concatenate(o.distance)
            view = np.concatenate(o.view)
            elev = np.concatenate(o.elevation)
        else:
            P = np.zeros((0, 3))
            inten = dist = elev = np.zeros(0)
            view = np.zeros((0, 3))
        top_beam = float(np.max(state.lidar_table)) - np.radians(TOP_BEAM_MARGIN_DEG)
        lidar_cut = np.zeros(0, bool)
        lidar_pts = np.zeros((0, 3))
        lidar_n = np.zeros((0, 3))
        lidar_t = np.zeros((0, 3))
        lidar_rho = np.zeros(0)
        if P.shape[0] >= opts.knn + 1:
            first, inverse = ig.voxel_dedupe(P, opts.voxel)
            nv = first.size
            centres = ig.group_mean(P, inverse, nv)
            vmean = ig.group_mean(view, inverse, nv)
            take = np.sort(rng.choice(nv, m, replace=False)) if nv > m else np.arange(nv)
            slot = np.full(nv, -1, np.int64)
            slot[take] = np.arange(take.size)
            if take.size >= opts.knn + 1:
                idx, _ = ig.knn(centres[take], opts.knn)
                nrm, tan, _ = ig.pca_frames(centres[take], idx)
                nrm = ig.orient_towards(nrm, vmean[take])
                ps = slot[inverse]
                u = ps >= 0
                cos = np.abs(np.sum(nrm[ps[u]] * view[u], axis=1))
                lidar_rho = ig.group_mean(ig.lidar_albedo(inten[u], dist[u], cos, kind, ref),
                                          ps[u], take.size)
                lidar_pts, lidar_n, lidar_t = centres[take], nrm, tan
                # A Gaussian is cut when any of its voxel's points was.
                cut_vox = np.zeros(nv, bool)
                np.logical_or.at(cut_vox, inverse, elev >= top_beam)
                lidar_cut = cut_vox[take]
        ext_pts, ext_n, ext_t, ext_seed = extend_object_top(
            lidar_pts, lidar_n, lidar_t, lidar_cut, opts.object_headroom)
        n_fill = m - lidar_pts.shape[0]
        fill_pts, fill_n = box_surface_samples(o.half_extent, n_fill, rng)
        helper = np.where(np.abs(fill_n[:, 2:3]) > 0.5, [[1.0, 0, 0]], [[0, 0, 1.0]])
        fill_t = np.cross(fill_n, helper)
        pts = np.concatenate([lidar_pts, fill_pts, ext_pts])
        normals = np.concatenate([lidar_n, fill_n, ext_n])
        tangents = np.concatenate([lidar_t, fill_t, ext_t])
        fill_rho = np.median(lidar_rho) if lidar_rho.size else 0.5
        rho = np.concatenate([lidar_rho, np.full(n_fill, fill_rho), lidar_rho[ext_seed]])
        _, dist_nn = ig.knn(pts, min(opts.knn, len(pts)))
        scales = ig.tangent_scales(dist_nn, smallest=0.2 * opts.voxel, largest=0.3)
        clouds[o.name] = {"centers": pts.astype(np.float32), "scales": scales,
                          "quaternions": ig.frames_to_quaternions(tangents, normals).astype(np.float32),
                          "normals": normals.astype(np.float32),
                          "lidar_albedo": np.clip(rho, 0, 1).astype(np.float32),
                          "from_lidar": int(lidar_pts.shape[0])}
        log("[import] %s (%s, %.1fx%.1fx%.1f m): %d Gaussians, %d from LiDAR points, "
            "%d on the box surface, %d above the top beam's cut"
            % (o.name, o.kind, *o.size_hwl[::-1], len(pts), lidar_pts.shape[0], n_fill,
               len(ext_pts)))
        for r in state.object_report:
            if r["track_id"] == o.track_id:
                r["gaussians_from_lidar"] = int(lidar_pts.shape[0])
                r["gaussians_above_top_beam"] = int(len(ext_pts))
    state.object_clouds = clouds
    state.counts["objects"] = len(clouds)


# -- colours -----------------------------------------------------------------------------

def _colours(state: ImportState, opts, log):
    from .kitti import srgb_to_linear

    K = state.K
    W, H = state.size
    block = max(1, int(round(W / 320)))
    bg = state.background["centers"]
    acc_bg = ig.ColourAccumulator(len(bg))
    objs = [o for o in state.objects if o.name in state.object_clouds]
    acc_obj = {o.name: ig.ColourAccumulator(len(state.object_clouds[o.name]["centers"]))
               for o in objs}
    for i, cam in enumerate(state.cam_poses):
        if held_out(i):     # held-out images are for `eval` alone
            continue
        w2c = np.linalg.inv(cam)
        clouds = [("", bg)]
        for o in objs:
            if o.active(i):
                c = state.object_clouds[o.name]["centers"]
                T = o.poses[i]
                clouds.append((o.name, ig.transform_points(c, T)))
        pts = np.concatenate([c for _, c in clouds])
        uv, z, ok = ig.project(pts, w2c, K, (W, H))
        vis = ig.ColourAccumulator.visible(uv, z, ok, (W, H), block)
        image = srgb_to_linear(state.images[i].astype(np.float32) / 255.0)
        start = 0
        for name, c in clouds:
            sl = slice(start, start + len(c))
            acc = acc_bg if name == "" else acc_obj[name]
            acc.add(np.arange(len(c)), uv[sl], z[sl], vis[sl], image)
            start += len(c)
    state.background["albedo"] = acc_bg.mean(0.5)
    seen = float(acc_bg.seen.mean()) if len(bg) else 0.0
    state.counts["background_coloured_fraction"] = seen
    for o in objs:
        state.object_clouds[o.name]["albedo"] = acc_obj[o.name].mean(0.5)
    log("[import] %.1f%% of the background Gaussians seen by a camera (others grey 0.5)"
        % (100 * seen))


# -- write -----------------------------------------------------------------------------

def _cloud(d, opts, source):
    from ..physics.gaussian_ply import GaussianCloud

    n = len(d["centers"])
    return GaussianCloud(
        centers=d["centers"], scales=d["scales"], quaternions=d["quaternions"],
        opacities=np.full(n, opts.opacity, np.float32), normals=d["normals"],
        albedo=d["albedo"], roughness=np.full(n, opts.roughness, np.float32),
        lidar_albedo=d["lidar_albedo"], sun_visibility=np.ones(n, np.float32),
        source=source).validate()


#: The explicit ray pattern of a non-spinning sensor, next to scene.xml:
#: (N, 7) origin, unit direction (sensor frame) and beam of each ray.
LIDAR_RAYS_FILE = "lidar_rays.npy"


def _write(src, state: ImportState, opts, tmp: Path, scene_name: str, data):
    """Everything into ``tmp``: PLYs, observations, frames.json, scene.xml."""
    from ..scene.frames import Frames
    from ..scene.imported import imported_scene

    objects = _write_clouds(state, opts, tmp)
    if state.lidar_rays is not None:
        np.save(tmp / LIDAR_RAYS_FILE, state.lidar_rays)
    records = _write_observations(src, state, tmp / "observations", list(objects))
    camera, lidar, extra = _sensors_and_notes(src, state, opts)
    gt = src.gt_dir.absolute() if src.gt_dir is not None else None
    frames = Frames(tmp / "frames.json", str(Path(data).absolute()), camera, lidar, objects,
                    gt, records, extra=extra)
    frames.save(tmp / "frames.json")
    comment = ("Imported by mi-invrgbl import from %s (%d frames). Per-frame sensors "
               "camera_NNNN / lidar_NNNN; dynamic objects at frame 0 (see frames.json and "
               "mi_invrgbl.scene.posing.set_frame)." % (Path(data).absolute(), len(records)))
    imported_scene(frames, tmp / scene_name, sky_order=opts.sky_order,
                   sun_irradiance=opts.sun_irradiance, comment=comment).write(str(tmp / scene_name))
    return frames


def _write_motion_masks(state: ImportState, frames, tmp: Path) -> int:
    """The motion masks (io/motion.py), listed in frames.json; the number of
    frames with anything masked."""
    from .motion import write_masks

    for rec, paths in zip(frames, write_masks(state, tmp)):
        rec.masks = dict(paths)
    frames.save(tmp / "frames.json")
    return state.counts.get("motion_masked_frames", 0)


def _write_clouds(state: ImportState, opts, tmp: Path) -> dict:
    """background.ply and one PLY per kept object; the objects' records."""
    from ..physics.gaussian_ply import write_ply
    from ..scene.frames import ObjectRecord

    write_ply(str(tmp / "background.ply"), _cloud(state.background, opts, "background"))
    objects = {}
    for o in state.objects:
        if o.name not in state.object_clouds:
            continue
        ply = tmp / f"{o.name}.ply"
        write_ply(str(ply), _cloud(state.object_clouds[o.name], opts, o.name))
        objects[o.name] = ObjectRecord(
            name=o.name, track_id=o.track_id, kind=o.kind,
            size_hwl=[float(v) for v in o.size_hwl], moving=bool(o.moving), ply=ply,
            extra={"labelled_frames": [int(i) for i in np.nonzero(o.labelled)[0]],
                   "displacement_m": round(float(o.displacement_m), 4),
                   "gaussians_from_lidar": state.object_clouds[o.name]["from_lidar"],
                   "frame": "origin at the box centre, x forward (length), y left, z up"})
    return objects


def _write_observations(src, state: ImportState, obs: Path, object_names) -> list:
    """Per frame: the image, the LiDAR range image and points; the frame records."""
    import cv2
    from ..scene.frames import FrameRecord
    from .images import write_exr

    drive = src.drive
    obs.mkdir()
    tracks = {o.name: o for o in state.objects if o.name in object_names}
    ts = drive.timestamps
    records = []
    for i, p in enumerate(state.positions):
        name = "%04d" % i
        src_img = Path(drive.image_paths[p])
        img_out = obs / f"image_{name}.png"
        if src_img.suffix.lower() == ".png" and state.images[i].shape[:2] == \
                tuple(drive.image_size[::-1]):
            shutil.copyfile(src_img, img_out)
        else:
            cv2.imwrite(str(img_out), state.images[i][:, :, ::-1])
        ri = state.range_images[i]
        write_exr(str(obs / f"lidar_{name}.exr"),
                  np.stack([ri.intensity, ri.range, ri.hit.astype(np.float32)], axis=-1),
                  ["intensity", "range", "hit"])
        np.save(obs / f"points_{name}.npy", state.world_points[i])
        if ts is not None:
            time_s = float(ts[p] - ts[state.positions[0]])
        else:
            time_s = 0.1 * (p - state.positions[0])
        records.append(FrameRecord(
            index=i, time=round(time_s, 6), held_out=held_out(i),
            camera=f"camera_{name}", lidar=f"lidar_{name}",
            image=img_out, lidar_scan=obs / f"lidar_{name}.exr",
            points=obs / f"points_{name}.npy",
            camera_to_world=state.cam_poses[i], lidar_to_world=state.poses[i],
            objects={n: o.poses[i] for n, o in tracks.items()},
            extra={"source_frame": int(drive.frames[p])}))
    return records


def _sensors_and_notes(src, state: ImportState, opts):
    """frames.json's camera and LiDAR records and its top-level notes."""
    from ..scene.frames import CameraInfo, LidarInfo

    K = state.K
    W, H = state.size
    kind, _ = state.intensity
    camera = CameraInfo(W, H, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                        extra={"image_scale": opts.image_scale}
                        | ({"source_crop_wh": list(state.crop)} if state.crop else {}))
    rays = state.lidar_rays
    lidar = LidarInfo(state.beams, opts.azimuth_steps if rays is None else len(rays),
                      [round(float(np.degrees(e)), 6) for e in state.lidar_table], kind,
                      extra={"far_clip": 120.0} | ({} if rays is None else {"rays": LIDAR_RAYS_FILE}))
    extra = {"pose_source": state.pose_source,
             "world_frame": "the first imported frame's LiDAR frame (x forward, y left, z up)",
             "tracks": state.object_report,
             "import": {k: v for k, v in vars(opts).items() if k not in ("overwrite", "verify")}}
    if state.skipped:
        extra["skipped_source_frames"] = state.skipped
    syn = src.synthetic or {}
    if src.gt_dir is not None and "world_from_velo" in syn:
        first = int(src.drive.frames[state.positions[0]])
        extra["gt_world_from_world"] = np.asarray(syn["world_from_velo"][first]).tolist()
    return camera, lidar, extra


def _verify(scene_path: Path):
    import mitsuba as mi

    try:
        scene = mi.load_file(str(scene_path))
    except Exception as exc:  # noqa: BLE001 - report any load failure as the import's fault
        raise RuntimeError(f"{scene_path}: the written scene does not load: {exc}") from exc
    n = len(scene.sensors())
    del scene
    return n
