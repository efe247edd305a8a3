"""Variant checks and plugin registration.

Mitsuba registers Python plugins per variant, and the plugin classes derive from
the variant's own ``mi.BSDF``/``mi.Emitter``/... classes, so a variant change has
to re-import the plugin modules and register them again. That is done from a
variant callback installed on first import.
"""

from __future__ import annotations

import importlib
import os

import mitsuba as mi

#: Plugin modules in ``mi_invrgbl.plugins``; each defines ``register()``.
PLUGIN_MODULES = (
    "cooktorrance",
    "shsun",
    "laser",
    "lidar",
    "gaussians",
    "lidar_return",
    "invrgbl",
)

#: Oldest libLLVM that Dr.Jit's LLVM backend can use for Mitsuba's kernels.
#: Debian 12's default LLVM 14/15 abort the process ("Cannot select ...
#: fminimum") inside Mitsuba's own ``path`` integrator.
MIN_LLVM_MAJOR = 16

LLVM_FIX = ("install Debian's libllvm19 (apt-get install libllvm19) or point "
            "DRJIT_LIBLLVM_PATH at a libLLVM >= %d" % MIN_LLVM_MAJOR)


class UnsupportedVariantError(RuntimeError):
    """Raised when the active Mitsuba variant or its backend cannot run the plugins."""


def _llvm_problem() -> str | None:
    """Return a one-sentence description of an unusable libLLVM, or None."""
    import drjit as dr
    try:
        version = dr.detail.llvm_version()
    except Exception:  # no LLVM backend could be initialised at all
        version = None
    if version is None:
        return ("Dr.Jit found no libLLVM for the LLVM backend; " + LLVM_FIX + ".")
    if version[0] < MIN_LLVM_MAJOR:
        path = os.environ.get("DRJIT_LIBLLVM_PATH", "the system default")
        return ("Dr.Jit loaded libLLVM %d.%d (%s), which aborts the process inside "
                "Mitsuba's kernels; %s." % (version[0], version[1], path, LLVM_FIX))
    return None


def check_variant(variant: str | None = None) -> str:
    """Check that ``variant`` (default: the active one) can run the plugins.

    Raises :class:`UnsupportedVariantError` with a single clear sentence for no
    variant, a scalar or non-RGB variant, or an unusable libLLVM.
    """
    variant = variant or mi.variant()
    if variant is None:
        raise UnsupportedVariantError(
            "mi_invrgbl needs a Mitsuba variant: call mi.set_variant('llvm_ad_rgb') "
            "(or 'cuda_ad_rgb') before importing it.")
    if not (variant.startswith("llvm_") or variant.startswith("cuda_")) or "_ad_" not in variant:
        raise UnsupportedVariantError(
            "mi_invrgbl needs a JIT autodiff variant such as 'llvm_ad_rgb' or "
            "'cuda_ad_rgb', not '%s'." % variant)
    if not variant.endswith("_rgb"):
        raise UnsupportedVariantError(
            "mi_invrgbl's plugins are RGB plugins: use 'llvm_ad_rgb' or 'cuda_ad_rgb', "
            "not '%s'." % variant)
    if variant.startswith("llvm_"):
        problem = _llvm_problem()
        if problem:
            raise UnsupportedVariantError(problem)
    return variant


def activate(name: str) -> None:
    """``mi.set_variant(name)``, as one clear :class:`UnsupportedVariantError`
    where the machine cannot run it (no CUDA GPU for a ``cuda_`` variant)."""
    if name.startswith("cuda_"):
        import drjit as dr
        if not dr.has_backend(dr.JitBackend.CUDA):
            raise UnsupportedVariantError(
                "variant '%s' needs an NVIDIA GPU with a working CUDA driver, and Dr.Jit "
                "found none on this machine; use -m llvm_ad_rgb (the CPU)" % name)
    try:
        mi.set_variant(name)
    except (ImportError, RuntimeError) as exc:
        raise UnsupportedVariantError("Mitsuba cannot start variant '%s' here: %s"
                                      % (name, " ".join(str(exc).split()))) from None


_callback_installed = False


def register_plugins() -> None:
    """(Re-)register every plugin for the active variant."""
    global _callback_installed
    for name in PLUGIN_MODULES:
        module = importlib.import_module("mi_invrgbl.plugins." + name)
        # The module's classes were built against the variant active at its
        # first import; reload so they derive from the current variant's bases.
        if getattr(module, "_variant", None) != mi.variant():
            module = importlib.reload(module)
        module.register()
    if not _callback_installed:
        mi.detail.add_variant_callback(_on_variant_change)
        _callback_installed = True


def _on_variant_change(old: str | None, new: str | None) -> None:
    if new is None:
        return
    try:
        check_variant(new)
    except UnsupportedVariantError:
        # Scalar/spectral variants are legal in Mitsuba; our plugins simply
        # are not available there. Loading a scene that names them then fails
        # with Mitsuba's "unknown plugin" error.
        return
    register_plugins()
