"""``mi-invrgbl import DATA -o DIR/scene.xml``: a drive -> an editable Mitsuba scene.

DATA is a KITTI raw drive (``DATE/DRIVE_sync`` with ``image_02``,
``velodyne_points`` and the date folder's calibration; poses from ``oxts``
or, without it, LiDAR odometry) or a KITTI odometry root (``sequences/XX``,
optional ``poses/XX.txt``, tracking labels ``label_02/XXXX.txt`` and the
synthetic street's ``gt/``); the layout is detected. The output follows
``docs/scene_format.md``; see :mod:`mi_invrgbl.io.importer` for the steps.
"""

from __future__ import annotations

import sys
import warnings


def add_parser(subparsers):
    from ..io.importer import ImportOptions
    d = ImportOptions()
    p = subparsers.add_parser(
        "import", help="turn a KITTI raw drive or odometry sequence into a Mitsuba scene",
        description="Import a camera + LiDAR drive (KITTI raw, or the KITTI odometry layout "
                    "that 'make-scene street' writes) as a Mitsuba scene of Gaussians with "
                    "per-frame camera and LiDAR sensors, an SH sky and the observations.")
    p.add_argument("data", metavar="DATA", help="KITTI raw drive folder or KITTI odometry root")
    p.add_argument("-o", "--output", required=True, metavar="DIR/scene.xml",
                   help="scene file to write; DIR must not exist yet (or pass --overwrite)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frame positions to import, Python slice syntax (default: all)")
    p.add_argument("--max-points", type=int, default=d.max_points,
                   help="most background Gaussians, random subsample (default %(default)s)")
    p.add_argument("--voxel", type=float, default=d.voxel,
                   help="dedupe voxel size in metres (default %(default)s)")
    p.add_argument("--azimuth-steps", type=int, default=d.azimuth_steps,
                   help="LiDAR range image width = lidar sensor film width (default %(default)s)")
    p.add_argument("--image-scale", type=float, default=d.image_scale,
                   help="downscale images and intrinsics, e.g. 0.25 for KITTI (default %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")
    p.add_argument("--dynamic", choices=("moving", "all", "none"), default=d.dynamic,
                   help="tracked objects that get their own node (default %(default)s)")
    p.add_argument("--object-points", type=int, default=d.object_points,
                   help="Gaussians per dynamic object (default %(default)s)")
    p.add_argument("--knn", type=int, default=d.knn,
                   help="neighbouring Gaussians for scales and tangents (default %(default)s)")
    p.add_argument("--normal-knn", type=int, default=d.normal_knn,
                   help="neighbouring voxels (before thinning to --max-points) whose PCA gives each "
                        "Gaussian's normal; 0: its --knn neighbouring Gaussians (default %(default)s)")
    p.add_argument("--opacity", type=float, default=d.opacity,
                   help="initial opacity (default %(default)s)")
    p.add_argument("--roughness", type=float, default=d.roughness,
                   help="roughness stage 2 starts from (GGX alpha in [0.02, 1]; default %(default)s)")
    p.add_argument("--min-range", type=float, default=d.min_range,
                   help="ignore closer LiDAR points for the background (default %(default)s m)")
    p.add_argument("--max-range", type=float, default=d.max_range,
                   help="ignore farther LiDAR points for the background (default %(default)s m)")
    p.add_argument("--intensity", choices=("auto", "raw", "reflectivity"), default=d.intensity,
                   help="LiDAR intensity kind (auto: KITTI -> reflectivity, synthetic -> raw)")
    p.add_argument("--beams", type=int, default=None, help="LiDAR beams (default: from the data, 64)")
    p.add_argument("--sky-order", type=int, default=d.sky_order,
                   help="SH order of the initial sky (default %(default)s)")
    p.add_argument("--no-triangulate", dest="triangulate", action="store_false",
                   help="no camera-only Gaussians from multi-view triangulation of the "
                        "training images (surfaces above the top beam and beyond range)")
    p.add_argument("--no-motion", dest="motion", action="store_false",
                   help="on drives without tracking labels, do not look for moving objects "
                        "in the LiDAR sweeps (rigid nodes, or masks the fit leaves out)")
    p.add_argument("--follow-nodes", action="store_true",
                   help="follow each moving object found in the LiDAR past its track, by "
                        "registering its points to the sweeps before and after (a vehicle that "
                        "stops or starts); off by default")
    p.add_argument("--extend-walls", type=float, default=d.extend_walls,
                   help="extend facades cut by the LiDAR's top beam upward by this many metres, "
                        "so the cameras' view above the LiDAR has Gaussians (default %(default)s; 0: off)")
    p.add_argument("--object-headroom", type=float, default=d.object_headroom,
                   help="continue a moving object whose LiDAR points the top beam cut (a truck "
                        "beside the car) this many metres up (default %(default)s; 0: off)")
    p.add_argument("--check-odometry", action="store_true",
                   help="also run LiDAR odometry on a drive with poses and report its error")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--no-verify", action="store_true",
                   help="skip loading the written scene with mi.load_file")
    p.set_defaults(run=run)
    return p


def options_from_args(args):
    from ..io.importer import ImportOptions
    return ImportOptions(
        frames=args.frames, max_points=args.max_points, voxel=args.voxel,
        azimuth_steps=args.azimuth_steps, image_scale=args.image_scale, seed=args.seed,
        dynamic=args.dynamic, object_points=args.object_points, knn=args.knn, normal_knn=args.normal_knn,
        opacity=args.opacity, roughness=args.roughness,
        min_range=args.min_range, max_range=args.max_range,
        intensity=args.intensity, beams=args.beams, sky_order=args.sky_order,
        extend_walls=args.extend_walls, object_headroom=args.object_headroom,
        triangulate=args.triangulate,
        motion=args.motion, follow_nodes=args.follow_nodes,
        check_odometry=args.check_odometry, overwrite=args.overwrite,
        verify=not args.no_verify)


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    print("mi-invrgbl import: warning: %s" % message, file=sys.stderr)


def run(args) -> int:
    from ..io.importer import import_scene
    with warnings.catch_warnings():
        warnings.simplefilter("always", UserWarning)
        warnings.showwarning = _one_line_warning
        report = import_scene(args.data, args.output, options_from_args(args))
    print("[import] step times:")
    for name, t in report.times.items():
        print("  %-12s %8.2f s" % (name, t))
    print("[import] counts: " + ", ".join("%s %s" % (k, ("%.3f" % v) if isinstance(v, float)
                                                      else v) for k, v in report.counts.items()))
    if report.odometry:
        print("[import] odometry: " + ", ".join(
            "%s %s" % (k, ("%.3f" % v) if isinstance(v, float) else v)
            for k, v in report.odometry.items()))
    print("[import] wrote %s" % report.scene)
    return 0
