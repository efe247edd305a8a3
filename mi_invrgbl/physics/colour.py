"""Colour constants and the sRGB curve, shared by the physics, the fit, the
readers and writers, and the metrics."""

import numpy as np

#: Luminance weights of linear sRGB / Rec. 709 primaries (Y of CIE XYZ).
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


#: The sRGB transfer function's constants (IEC 61966-2-1): linear below the
#: knee with this slope, ``(1 + A) x^(1 / GAMMA) - A`` above it. The fit's
#: camera loss (``fit.losses.srgb_encode``) applies the same curve in Dr.Jit.
SRGB_KNEE, SRGB_SLOPE, SRGB_A, SRGB_GAMMA = 0.0031308, 12.92, 0.055, 2.4


def linear_to_srgb(x):
    """The sRGB transfer function (IEC 61966-2-1) on linear values (not clipped)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= SRGB_KNEE, SRGB_SLOPE * x,
                    (1 + SRGB_A) * np.power(np.maximum(x, SRGB_KNEE), 1 / SRGB_GAMMA) - SRGB_A)


def srgb_to_linear(x):
    """Inverse of :func:`linear_to_srgb`."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, np.power((np.maximum(x, 0.04045) + 0.055) / 1.055, 2.4))
