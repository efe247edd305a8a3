"""Options of the street generator and their validation."""

from __future__ import annotations

import dataclasses
import os

from ..errors import UserError


#: BSDFs the street's materials can be rendered with.
BSDFS = ("roughplastic", "cooktorrance")


@dataclasses.dataclass
class StreetConfig:
    """Everything that changes the generated street; same values -> same bytes."""

    seed: int = 0
    frames: int = 24
    width: int = 320            #: camera image width (pixels)
    height: int = 96            #: camera image height (pixels)
    fov: float = 80.0           #: horizontal field of view (degrees)
    spp: int = 32               #: samples per pixel of the RGB renders
    max_depth: int = 4          #: path length of the stock ``path`` integrator
    beams: int = 64             #: LiDAR beams (rows of the range image)
    azimuth_steps: int = 1024   #: LiDAR columns per sweep
    step: float = 1.0           #: ego travel per frame (metres)
    frame_rate: float = 10.0    #: frames per second (times.txt)
    night: bool = True          #: also render the night images
    bsdf: str = "roughplastic"  #: roughplastic (Mitsuba's) | cooktorrance (the paper's model)
    lidar: str = "hdl64"        #: hdl64 | vlp32 | os128 | rays:FILE (see :mod:`.sensors`)
    intensity: str = "raw"      #: raw return strength | reflectivity (range-compensated)

    def validate(self) -> "StreetConfig":
        """Raise :class:`UserError` naming the first bad option."""
        checks = [
            ("--frames", self.frames, 1), ("--width", self.width, 8),
            ("--height", self.height, 8), ("--spp", self.spp, 1),
            ("--max-depth", self.max_depth, 1), ("--beams", self.beams, 2),
            ("--azimuth-steps", self.azimuth_steps, 8),
        ]
        for name, value, low in checks:
            if int(value) < low:
                raise UserError("%s must be at least %d (got %s)" % (name, low, value))
        if not 10.0 <= self.fov <= 150.0:
            raise UserError("--fov must lie between 10 and 150 degrees (got %s)" % self.fov)
        if not 0.0 < self.step <= 5.0:
            raise UserError("--step must lie in (0, 5] metres (got %s)" % self.step)
        if self.bsdf not in BSDFS:
            raise UserError("--bsdf must be one of %s (got %r)" % (", ".join(BSDFS), self.bsdf))
        from .sensors import load_rays, parse_lidar
        kind, path = parse_lidar(self.lidar)
        if path is not None:
            load_rays(path)
        if self.intensity not in ("raw", "reflectivity"):
            raise UserError("--intensity must be raw or reflectivity (got %r)" % self.intensity)
        if self.seed < 0:
            raise UserError("--seed must be non-negative (got %s)" % self.seed)
        return self


def check_output(out: str) -> tuple[str, str]:
    """Return (absolute OUT, its parent) or raise :class:`UserError`.

    OUT must not exist yet (the generator never overwrites a finished street)
    and its parent must be a writable directory, because the street is written
    into a temporary sibling folder and renamed at the end.
    """
    out = os.path.abspath(out)
    parent = os.path.dirname(out)
    if os.path.exists(out):
        raise UserError("output '%s' already exists; choose a new folder or remove it" % out)
    if not os.path.isdir(parent):
        raise UserError("parent folder '%s' of the output does not exist" % parent)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError("cannot write into '%s' (permission denied)" % parent)
    return out, parent
