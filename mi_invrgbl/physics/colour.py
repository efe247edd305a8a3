"""Colour constants shared by the physics, the fit and the readers."""

import numpy as np

#: Luminance weights of linear sRGB / Rec. 709 primaries (Y of CIE XYZ).
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
