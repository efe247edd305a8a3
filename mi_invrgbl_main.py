"""Entry point of the ``mi-invrgbl`` console script.

``import mi_invrgbl`` requires a Mitsuba variant to be chosen first (it
registers the plugins for it), so the command picks the variant named by
``-m/--variant`` before importing the package.
"""

import os
import sys


def _variant_from_argv(argv):
    for i, arg in enumerate(argv):
        if arg in ("-m", "--variant") and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--variant="):
            return arg.split("=", 1)[1]
    # $MI_INVRGBL_VARIANT lets a test suite or a GPU machine change the default.
    return os.environ.get("MI_INVRGBL_VARIANT") or "llvm_ad_rgb"


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    import mitsuba as mi
    variant = _variant_from_argv(argv)
    if variant in mi.variants():
        try:
            if variant.startswith("cuda_"):
                import drjit as dr
                if not dr.has_backend(dr.JitBackend.CUDA):
                    raise RuntimeError(
                        "variant '%s' needs an NVIDIA GPU with a working CUDA driver, and "
                        "Dr.Jit found none on this machine; use -m llvm_ad_rgb (the CPU)" % variant)
            mi.set_variant(variant)
            import mi_invrgbl  # noqa: F401  (registers the plugins)
        except (ImportError, RuntimeError) as exc:  # no GPU, unusable libLLVM: one line
            print("mi-invrgbl: error: -m %s: %s" % (variant, " ".join(str(exc).split())),
                  file=sys.stderr)
            return 2
    else:
        print("mi-invrgbl: error: unknown Mitsuba variant '%s' (available: %s)"
              % (variant, ", ".join(v for v in mi.variants() if "_ad_rgb" in v)),
              file=sys.stderr)
        return 2
    from mi_invrgbl.cli import main as cli_main
    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
