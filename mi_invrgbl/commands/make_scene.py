"""``mi-invrgbl make-scene street OUT``: a synthetic street with full ground truth.

Writes a KITTI odometry + tracking layout (images, LiDAR sweeps, calibration,
poses, labels) plus the true materials, lights, per-pixel maps and the
Mitsuba scenes that produced the images; see
:mod:`mi_invrgbl.synthetic.generator` for the layout.
"""

from __future__ import annotations

from ..errors import UserError

KINDS = ("street",)


def add_parser(subparsers):
    from ..synthetic.config import StreetConfig
    d = StreetConfig()
    p = subparsers.add_parser(
        "make-scene", help="generate a synthetic street with ground truth (KITTI layout)",
        description="Generate a seeded synthetic street scene: RGB renders at two times of "
                    "day and at night, LiDAR sweeps (HDL-64, VLP-32C, OS1-128 or an explicit ray pattern), KITTI calib/poses/labels and "
                    "ground-truth material, normal, depth and sun-visibility maps.")
    p.add_argument("kind", choices=KINDS, help="scene kind (only 'street' for now)")
    p.add_argument("out", metavar="OUT", help="output folder (must not exist yet)")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")
    p.add_argument("--frames", type=int, default=d.frames, help="frames (default %(default)s)")
    p.add_argument("--width", type=int, default=d.width, help="image width (default %(default)s)")
    p.add_argument("--height", type=int, default=d.height, help="image height (default %(default)s)")
    p.add_argument("--fov", type=float, default=d.fov,
                   help="horizontal field of view in degrees (default %(default)s)")
    p.add_argument("--spp", type=int, default=d.spp, help="samples per pixel (default %(default)s)")
    p.add_argument("--max-depth", type=int, default=d.max_depth,
                   help="path integrator max_depth (default %(default)s)")
    p.add_argument("--beams", type=int, default=d.beams, help="LiDAR beams (default %(default)s)")
    p.add_argument("--azimuth-steps", type=int, default=d.azimuth_steps,
                   help="LiDAR azimuth steps per sweep (default %(default)s)")
    p.add_argument("--step", type=float, default=d.step,
                   help="ego travel per frame in metres (default %(default)s)")
    p.add_argument("--no-night", action="store_true", help="skip the night renders")
    p.add_argument("--bsdf", choices=("roughplastic", "cooktorrance"), default=d.bsdf,
                   help="BSDF of the true materials: Mitsuba's roughplastic (default) or the "
                        "paper's cooktorrance, the family 'fit' searches")
    p.add_argument("--lidar", default=d.lidar, metavar="SENSOR",
                   help="LiDAR: hdl64 (default), vlp32 (non-uniform 32-beam table), os128, or "
                        "rays:FILE (an explicit (N, 6) or (N, 7) ray list in the sensor frame)")
    p.add_argument("--intensity", choices=("raw", "reflectivity"), default=d.intensity,
                   help="LiDAR intensity: raw return strength (default) or range-compensated "
                        "reflectivity (as KITTI's HDL-64E reports)")
    p.set_defaults(run=run)
    return p


def config_from_args(args):
    from ..synthetic.config import StreetConfig
    return StreetConfig(seed=args.seed, frames=args.frames, width=args.width,
                        height=args.height, fov=args.fov, spp=args.spp,
                        max_depth=args.max_depth, beams=args.beams,
                        azimuth_steps=args.azimuth_steps, step=args.step,
                        night=not args.no_night, bsdf=args.bsdf, lidar=args.lidar,
                        intensity=args.intensity)


def run(args) -> int:
    import os
    from .. import outdir
    from ..synthetic import generate_street
    if args.kind != "street":
        raise UserError("unknown scene kind '%s'" % args.kind)
    cfg = config_from_args(args).validate()
    # The generator writes a temporary sibling and renames it; a finished
    # street is marked as this tool's and given the usual permissions.
    outdir.check_new_folder(args.out, "make-scene")
    generate_street(args.out, cfg)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(args.out, 0o777 & ~umask)
    outdir.mark(args.out, "make-scene")
    return 0
