"""The Mitsuba variant the test suite and the benches run in.

``MI_INVRGBL_VARIANT`` (or pytest's ``--variant``, which sets it) picks it;
``llvm_ad_rgb`` runs everywhere, ``cuda_ad_rgb`` needs an NVIDIA GPU. Tests
that start the ``mi-invrgbl`` command inherit the variable, and the command
uses it as its default ``--variant``.
"""

from __future__ import annotations

import os

DEFAULT = "llvm_ad_rgb"


def variant() -> str:
    return os.environ.get("MI_INVRGBL_VARIANT") or DEFAULT


def use(name: str | None = None) -> str:
    """Select ``name`` (default: :func:`variant`) in Mitsuba and return it, with
    one clear error when this machine cannot run it."""
    import mitsuba as mi
    name = name or variant()
    if name not in mi.variants():
        raise SystemExit("variant %r is not built into this Mitsuba (have: %s)"
                         % (name, ", ".join(mi.variants())))
    try:
        mi.set_variant(name)
    except Exception as exc:  # no GPU / driver for cuda_* variants
        raise SystemExit("variant %r cannot run on this machine: %s" % (name, exc))
    return name


def from_argv(argv: list | None = None) -> str:
    """For the benches: take ``--variant NAME`` out of ``argv`` (default
    ``sys.argv``), export it so ``mi-invrgbl`` subprocesses inherit it, and
    select it."""
    import sys
    argv = sys.argv if argv is None else argv
    for i, arg in enumerate(list(argv)):
        if arg == "--variant" and i + 1 < len(argv):
            os.environ["MI_INVRGBL_VARIANT"] = argv[i + 1]
            del argv[i:i + 2]
            break
        if arg.startswith("--variant="):
            os.environ["MI_INVRGBL_VARIANT"] = arg.split("=", 1)[1]
            del argv[i]
            break
    return use()
