"""Angles between directions, shared by the fit's log and reports, the
evaluation against the truth's sun, and the benches."""

import numpy as np


def angle_deg(a, b) -> float:
    """Degrees between directions ``a`` and ``b`` (3-vectors, any length).

    Each is normalised first, and the cosine clipped to [-1, 1] so that
    rounding never yields NaN for (anti)parallel directions. A zero vector
    has no direction: the answer is then NaN rather than a made-up angle.
    """
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    if a.shape != (3,) or b.shape != (3,):
        raise ValueError("angle_deg: expected two 3-vectors, got shapes %s and %s"
                         % (a.shape, b.shape))
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if not (na > 0 and nb > 0 and np.isfinite(na) and np.isfinite(nb)):
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))
