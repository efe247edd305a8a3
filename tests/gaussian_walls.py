"""Walls of flat Gaussians facing -x, for tests that trace rays through them."""

import numpy as np
import mitsuba as mi


def wall(shape_id, x, y_range, z_range, colour, opacity, spacing=0.1, seed=2):
    """A ``gaussians`` shape dict: discs ``spacing`` apart on the plane
    ``x`` over ``y_range`` x ``z_range``, each 1.1 ``spacing`` wide, with
    normal -x, colour ``colour`` and opacity ``opacity``.

    Centres are jittered in depth too: discs entered at the same distance
    would hide each other from the traversal (it steps just past each
    entry point)."""
    ys = np.arange(y_range[0], y_range[1] + 1e-6, spacing)
    zs = np.arange(z_range[0], z_range[1] + 1e-6, spacing)
    Y, Z = np.meshgrid(ys, zs)
    c = np.stack([np.full(Y.size, x), Y.ravel(), Z.ravel()], 1).astype(np.float32)
    c += np.random.default_rng(seed).uniform(-0.03, 0.03, c.shape).astype(np.float32)
    n = c.shape[0]
    s = 1.1 * spacing
    t = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    return {"type": "gaussians", "id": shape_id, "centers": t(c),
            "scales": t(np.tile([[1e-3, s, s]], (n, 1))), "opacities": t(np.full(n, opacity)),
            "normals": t(np.tile([[-1.0, 0, 0]], (n, 1))), "albedo": t(np.tile([colour], (n, 1)))}
