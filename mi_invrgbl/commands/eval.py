"""``mi-invrgbl eval FIT_DIR_OR_SCENE``: score a (fitted) scene on its frames.

Parses the arguments and calls the evaluation library
(:func:`mi_invrgbl.eval.scoring.evaluate`, see :mod:`mi_invrgbl.eval` for
what is measured); writes ``metrics.json`` and prints a table.
"""

from __future__ import annotations

from pathlib import Path

from ..eval.inputs import resolve_inputs
from ..eval.scoring import EVAL_SPP, evaluate, format_table, write_metrics


def add_parser(sub):
    p = sub.add_parser("eval", help="score a fitted scene on held-out frames (and ground truth)")
    p.add_argument("scene", metavar="FIT_DIR_OR_SCENE",
                   help="a fit folder (with scene.xml) or a scene XML file")
    p.add_argument("--frames", default="held-out",
                   help="held-out (default), all, A:B (frame indices, B excluded) or a list 3,8")
    p.add_argument("-o", "--output", default=None,
                   help="metrics file (default: metrics.json next to the scene)")
    p.add_argument("--spp", type=int, default=EVAL_SPP,
                   help="camera samples per pixel (default %d: fewer add sampling noise to the "
                        "scores; 0: the sensor's own)" % EVAL_SPP)
    p.add_argument("--samples", type=int, default=None,
                   help="sky samples M of the invrgbl integrator (default: the scene's)")
    p.add_argument("--lidar-model", choices=("pbr", "lambertian"), default=None,
                   help="LiDAR model when the fit has no scene_lidar.xml (default: pbr)")
    p.add_argument("--no-baseline", action="store_true", help="skip the nearest-neighbour baseline")
    p.add_argument("--no-relight", action="store_true", help="skip the relighting score")
    p.add_argument("--save-renders", default=None, metavar="DIR",
                   help="also write each frame's renders (EXR) into DIR")
    p.set_defaults(run=run)


def _is_metrics_file(path) -> bool:
    """Whether ``path`` is a metrics.json that ``fit`` or ``eval`` wrote (folders
    written before output markers existed)."""
    from ..eval.inputs import read_json_dict
    data = read_json_dict(str(path))
    return data is not None and (data.get("format") == "mi-invrgbl-metrics/1"
                                 or ("selection" in data
                                     and bool({"wall_s", "heldout_psnr"} & set(data))))


def run(args):
    from .. import outdir
    scene_xml, _ = resolve_inputs(args.scene)
    out = args.output or Path(scene_xml).parent / "metrics.json"
    # Checked before the renders, not after them.
    outdir.check_file(out, "eval", inputs=[scene_xml], recognise=_is_metrics_file,
                      what="metrics file")
    renders = None
    if args.save_renders:
        renders = outdir.prepare(args.save_renders, "eval", inputs=[scene_xml],
                                 replace_own=True, what="--save-renders folder")
    try:
        result = evaluate(args.scene, args.frames, spp=args.spp, samples=args.samples,
                          lidar_model=args.lidar_model, baseline=not args.no_baseline,
                          relight=not args.no_relight,
                          save_renders=str(renders.path) if renders else None)
    except BaseException:
        if renders:
            renders.discard()
        raise
    if renders:
        renders.commit()
    out = write_metrics(result, out)
    outdir.register_file(out)
    print(format_table(result["frames"], result["mean"]))
    print("[eval] wrote %s" % out)
    return 0
