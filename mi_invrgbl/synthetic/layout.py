"""Street geometry: which meshes exist, where, and which material each uses.

World frame: z up, x along the street (the direction of travel), y to the
left; the road surface is z = 0. The ego car drives in the right lane.

Every static part is built directly in world coordinates; the moving car is
built in its own frame (x forward, y left, z up, origin at the centre of its
footprint) and placed per frame by :mod:`.trajectory`.

Besides the road, the street deliberately has structure in depth (buildings
set back by different amounts, protruding windows and balconies, a row of
poles and trees every ~15 m, gaps between buildings): LiDAR odometry finds
nothing to lock on in a corridor of flat facades. Measured with KISS-ICP
1.3 (voxel 0.5 m) on 24 default frames: with points more than 0.3 m above
the road it recovers the 23 m of travel to within 0.1 m; on full sweeps the
perfectly flat road's rings (which move with the sensor) dominate and it
reports almost no forward motion, so drop ground points before odometry.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from . import materials as mats

#: Lateral positions (y, metres) of the lane centres and road furniture.
EGO_LANE_Y = -1.75
OTHER_LANE_Y = 1.75
ROAD_HALF = mats.ROAD_WIDTH / 2
SIDEWALK_TOP = 0.15
SIDEWALK_OUTER = 30.0        #: sidewalks extend under the buildings
#: Street starts this far behind the first frame.
STREET_BEHIND = 30.0
#: ... and ends this far ahead of the last frame (beyond the LiDAR's far range).
STREET_AHEAD = 90.0

#: The uniform wall (half in the shadow of its canopy at time A).
WALL_X = (12.0, 20.0)
WALL_FRONT_Y = -7.0
WALL_HEIGHT = 4.0
WALL_DEPTH = 2.0

#: Car dimensions (KITTI order h, w, l) and the parked car's footprint centre.
CAR_HWL = (1.45, 1.8, 4.4)
PARKED_CAR_XY = (26.0, -3.9)


@dataclasses.dataclass
class Part:
    """One mesh of the street: its shape id, geometry and material name."""

    name: str
    mesh: trimesh.Trimesh
    material: str
    dynamic: bool = False


@dataclasses.dataclass
class Layout:
    parts: list
    materials: dict                 #: material name -> materials.Material
    lamps: list                     #: (position, direction) of the streetlight heads
    headlights: list                #: (position, direction) in the moving car's frame
    wall: dict                      #: geometry of the uniform wall, for tests and scoring
    x_range: tuple                  #: street extent along x


def box(x0, x1, y0, y1, z0, z1) -> trimesh.Trimesh:
    """Axis-aligned box between the given bounds (12 triangles)."""
    extents = (x1 - x0, y1 - y0, z1 - z0)
    centre = ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2)
    return trimesh.creation.box(extents=extents,
                                transform=trimesh.transformations.translation_matrix(centre))


def vertical_cylinder(x, y, z0, height, radius, sections=12) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    mesh.apply_translation((x, y, z0 + height / 2))
    return mesh


def merge(meshes) -> trimesh.Trimesh:
    return trimesh.util.concatenate(list(meshes))


def road(x0: float, x1: float) -> trimesh.Trimesh:
    """The road quad with UVs: u repeats every texture period, v spans the width."""
    verts = np.array([[x0, -ROAD_HALF, 0], [x1, -ROAD_HALF, 0],
                      [x1, ROAD_HALF, 0], [x0, ROAD_HALF, 0]], dtype=np.float64)
    uv = np.stack([verts[:, 0] / mats.ROAD_PERIOD,
                   (verts[:, 1] + ROAD_HALF) / mats.ROAD_WIDTH], axis=1)
    mesh = trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    return mesh


def car_body() -> trimesh.Trimesh:
    """A car in its own frame: lower body and cabin (x forward, origin on the ground)."""
    h, w, l = CAR_HWL
    lower = box(-l / 2, l / 2, -w / 2, w / 2, 0.3, 0.95)
    cabin = box(-l / 2 + 0.8, l / 2 - 1.2, -w / 2 + 0.1, w / 2 - 0.1, 0.95, h)
    return merge([lower, cabin])


def car_wheels() -> list:
    h, w, l = CAR_HWL
    wheels = []
    for dx in (-1.35, 1.35):
        for dy in (-w / 2 + 0.1, w / 2 - 0.1):
            cyl = trimesh.creation.cylinder(radius=0.3, height=0.22, sections=12)
            cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
            cyl.apply_translation((dx, dy, 0.3))
            wheels.append(cyl)
    return wheels


def _facade(index, side, x0, x1, rng, materials, windows):
    """One building: a box with a varied setback, protruding windows and balconies."""
    setback = rng.uniform(8.5, 13.0)
    depth = rng.uniform(6.0, 10.0)
    height = rng.uniform(5.0, 14.0 if side > 0 else 18.0)
    y_front = side * setback
    y_back = side * (setback + depth)
    parts = [box(x0, x1, min(y_front, y_back), max(y_front, y_back), 0.0, height)]
    balconies = rng.random() < 0.4
    floor = 0
    z = 1.0
    while z + 1.6 < height - 0.4:
        xc = x0 + 1.4
        while xc + 0.6 < x1 - 0.8:
            # Windows stand 6 cm proud of the facade (towards the street).
            yw0, yw1 = sorted((y_front, y_front - side * 0.06))
            windows.append(box(xc - 0.55, xc + 0.55, yw0, yw1, z, z + 1.5))
            if balconies and floor >= 1 and rng.random() < 0.5:
                yb0, yb1 = sorted((y_front, y_front - side * 1.0))
                parts.append(box(xc - 0.9, xc + 0.9, yb0, yb1, z - 0.15, z))
            xc += 2.2
        z += 3.0
        floor += 1
    mat = mats.facade_material(index, rng)
    materials[mat.name] = mat
    return Part(mat.name, merge(parts), mat.name)


def _buildings(rng, x_start, x_end, materials, windows):
    parts = []
    index = 0
    for side in (1, -1):
        x = x_start
        while x < x_end:
            width = rng.uniform(6.0, 14.0)
            x1 = min(x + width, x_end)
            # Keep the slot of the uniform wall free on the right side.
            if side < 0 and x1 > WALL_X[0] - 1.0 and x < WALL_X[1] + 1.0:
                x = WALL_X[1] + 1.0
                continue
            parts.append(_facade(index, side, x, x1, rng, materials, windows))
            index += 1
            x = x1 + (rng.uniform(1.5, 5.0) if rng.random() < 0.5 else 0.0)
    return parts


def _pole(x, y, towards_road):
    """A streetlight: mast, arm over the road and lamp head; returns (meshes, lamp)."""
    height = 6.0
    arm_end = y + towards_road * 1.6
    meshes = [vertical_cylinder(x, y, 0.0, height, 0.1),
              box(x - 0.05, x + 0.05, min(y, arm_end), max(y, arm_end), height - 0.1, height),
              box(x - 0.25, x + 0.25, arm_end - 0.2, arm_end + 0.2, height - 0.25, height - 0.1)]
    lamp = ((x, arm_end, height - 0.3), (0.0, 0.0, -1.0))
    return meshes, lamp


def _tree(x, y):
    trunk = vertical_cylinder(x, y, 0.0, 3.4, 0.2)
    crown = trimesh.creation.icosphere(subdivisions=2, radius=1.8)
    crown.apply_translation((x, y, 4.8))
    return trunk, crown


def wall_canopy_depth(sun_direction) -> float:
    """Canopy depth that shades exactly the upper half of the wall for this sun.

    A point at height z on the wall (plane y = WALL_FRONT_Y, facing +y) is in
    the canopy's shadow when its ray to the sun passes under the canopy edge:
    z >= WALL_HEIGHT - depth * s_z / s_y.
    """
    sx, sy, sz = sun_direction
    if sy <= 0.05:
        raise ValueError("sun A must shine on the wall (positive y component)")
    return (WALL_HEIGHT / 2) * sy / sz


def build(frames: int, step: float, rng: np.random.Generator, sun_a) -> Layout:
    """Build the street for a sequence of ``frames`` frames, ``step`` metres apart."""
    x_start = -STREET_BEHIND
    x_end = frames * step + STREET_AHEAD
    materials = mats.fixed_materials()
    parts = [Part("road", road(x_start, x_end), "road")]
    parts.append(Part("sidewalk", merge([
        box(x_start, x_end, ROAD_HALF, SIDEWALK_OUTER, -0.2, SIDEWALK_TOP),
        box(x_start, x_end, -SIDEWALK_OUTER, -ROAD_HALF, -0.2, SIDEWALK_TOP)]), "sidewalk"))

    windows = []
    parts += _buildings(rng, x_start, x_end, materials, windows)
    parts.append(Part("windows", merge(windows), "windows"))

    # Poles: the hero pole left of the road near the start (its shadow crosses
    # the road at time A), then one every ~14 m, alternating sides: posts
    # across the line of travel are what LiDAR odometry measures motion by.
    pole_meshes, lamps = [], []
    spots = [(10.0, 1), (28.0, -1)]
    x = 42.0
    side = 1
    while x < x_end - 10:
        spots.append((x + rng.uniform(-2, 2), side))
        x += 14.0
        side = -side
    for px, side in spots:
        meshes, lamp = _pole(px, side * (ROAD_HALF + 0.6), -side)
        pole_meshes += meshes
        lamps.append(lamp)
    parts.append(Part("poles", merge(pole_meshes), "poles"))

    trunks, crowns = [], []
    # The hero tree (left, near the start), then a tree every ~16 m, alternating sides.
    tree_spots = [(22.0, ROAD_HALF + 1.5)]
    x, side = 36.0, -1
    while x < x_end - 10:
        tree_spots.append((x + rng.uniform(-2, 2), side * (ROAD_HALF + 1.5)))
        x += 16.0
        side = -side
    for tx, ty in tree_spots:
        t, c = _tree(tx, ty)
        trunks.append(t)
        crowns.append(c)
    parts.append(Part("tree_trunk", merge(trunks), "tree_trunk"))
    parts.append(Part("tree_crown", merge(crowns), "tree_crown"))

    # The uniform wall with a canopy along its top that shades its upper half.
    depth = wall_canopy_depth(sun_a)
    parts.append(Part("wall", box(WALL_X[0], WALL_X[1], WALL_FRONT_Y - WALL_DEPTH, WALL_FRONT_Y,
                                  0.0, WALL_HEIGHT), "wall"))
    # The canopy overhangs the wall's ends by 3 m so that its shadow covers the
    # full width of the wall even though the sun also shines along x.
    parts.append(Part("canopy", box(WALL_X[0] - 3.0, WALL_X[1] + 3.0, WALL_FRONT_Y,
                                    WALL_FRONT_Y + depth, WALL_HEIGHT, WALL_HEIGHT + 0.12),
                      "canopy"))

    px, py = PARKED_CAR_XY
    body = car_body()
    body.apply_translation((px, py, 0.0))
    wheels = []
    for wmesh in car_wheels():
        wmesh.apply_translation((px, py, 0.0))
        wheels.append(wmesh)
    parts.append(Part("parked_car", body, "parked_car"))
    parts.append(Part("wheels", merge(wheels), "wheels"))
    parts.append(Part("moving_car", car_body(), "moving_car", dynamic=True))

    l = CAR_HWL[2]
    headlights = [((l / 2 + 0.05, dy, 0.7), (1.0, 0.0, -0.08)) for dy in (-0.6, 0.6)]
    wall = {"x": list(WALL_X), "front_y": WALL_FRONT_Y, "height": WALL_HEIGHT,
            "normal": [0.0, 1.0, 0.0], "canopy_depth": depth,
            "shadow_below_z": WALL_HEIGHT / 2}
    return Layout(parts, materials, lamps, headlights, wall, (x_start, x_end))
