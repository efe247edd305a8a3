"""The ``mi-invrgbl`` command.

Each sub-command lives in its own module under :mod:`mi_invrgbl.commands` and
provides ``add_parser(subparsers)`` and ``run(args) -> int``. Errors that a
user can fix (a bad file, a missing libLLVM, an unknown plugin parameter) are
raised as :class:`mi_invrgbl.errors.UserError` and printed as one line;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import UserError

#: Sub-command modules in the order ``--help`` lists them.
COMMANDS = ("render_sensors", "make_scene", "import_data", "fit", "eval", "relight",
            "night", "insert", "lidar")


def _available_commands():
    for name in COMMANDS:
        try:
            yield importlib.import_module("mi_invrgbl.commands." + name)
        except ModuleNotFoundError as exc:
            if exc.name != "mi_invrgbl.commands." + name:
                raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mi-invrgbl",
        description="InvRGB+L inverse rendering of camera + LiDAR scenes with Mitsuba 3.")
    parser.add_argument("-m", "--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant (default: llvm_ad_rgb; or cuda_ad_rgb)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in _available_commands():
        module.add_parser(sub)
    return parser


def set_variant(name: str) -> None:
    """Select the Mitsuba variant and register the plugins, as one clear error on failure."""
    import mitsuba as mi
    if name not in mi.variants():
        raise UserError("unknown Mitsuba variant '%s' (available: %s)"
                        % (name, ", ".join(v for v in mi.variants() if "_ad_rgb" in v)))
    from .variant import activate, check_variant, register_plugins, UnsupportedVariantError
    try:
        activate(name)
        check_variant(name)
    except UnsupportedVariantError as exc:
        raise UserError("-m %s: %s" % (name, exc)) from None
    register_plugins()


def main(argv=None) -> int:
    from . import outdir
    parser = build_parser()
    args = parser.parse_args(argv)
    outdir.command_line[:] = ["mi-invrgbl"] + list(sys.argv[1:] if argv is None else argv)
    try:
        set_variant(args.variant)
        return int(args.run(args) or 0)
    except UserError as exc:
        print("mi-invrgbl %s: error: %s" % (args.command, exc), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mi-invrgbl %s: interrupted" % args.command, file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
