"""Synthetic ground-truth street scenes (camera + LiDAR) for scoring InvRGB+L.

``mi-invrgbl make-scene street OUT`` builds a seeded street from trimesh meshes
with Mitsuba's stock BSDFs and emitters, renders it with Mitsuba's stock
``path`` integrator at two times of day and at night, simulates a 64-beam
LiDAR with the paper's reflectance model, and writes everything in the KITTI
odometry + tracking layout together with the true material, normal, depth and
sun-visibility maps that a fit is scored against.

Modules, one job each:

* :mod:`.config`     -- options and their validation
* :mod:`.materials`  -- the true material table and the road texture
* :mod:`.layout`     -- street geometry (meshes + which material each uses)
* :mod:`.trajectory` -- ego, camera, LiDAR and moving-car poses; KITTI frames
* :mod:`.lights`     -- sun/sky for time A and B, night lights
* :mod:`.scene_xml`  -- the Mitsuba scene files (one per lighting)
* :mod:`.rgb_frames` -- RGB rendering of every frame
* :mod:`.groundtruth`-- per-pixel ground-truth maps by ray casting
* :mod:`.lidar_sim`  -- LiDAR sweeps (intensity, range noise, ray drop)
* :mod:`.writers`    -- KITTI text/binary files, EXR and PNG
* :mod:`.generator`  -- runs the steps in order, timing each
"""

from .config import StreetConfig
from .generator import generate_street

__all__ = ["StreetConfig", "generate_street"]
