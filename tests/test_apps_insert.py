"""``mi-invrgbl insert``: the object appears at its pose, lit by the target scene, with shadows.

A small target scene (ground, a 6 m wall, a low sun behind the wall: the
wall's shadow covers the ground up to x = 8.6 m) is rendered by Mitsuba's
``path`` (mesh insertions) and by our ``invrgbl`` (a fitted node's Gaussians).

* pose: the pixels whose centre ray hits the inserted shape are centred on
  the projection of the object's centre (within ``POSE_PX`` pixels);
* lighting: a grey sphere's mean colour has the chromaticity of the target's
  light, under a warm sun and under a blue sky (within ``CHROMA_TOL``; all
  surfaces are grey, so inter-reflections do not tint it);
* shadows both ways: the object in the sun darkens the ground where it blocks
  the sun (cast; < ``CAST_RATIO`` of the ground's radiance without it), and
  the object in the wall's shadow is darker than in the sun (received;
  < ``RECEIVE_RATIO``).

Measured (96x64): pose error 0.2 px (mesh) / 0.5 px (Gaussians), chromaticity
error < 1e-4, cast ratio 0.20 (path) / 0.37 (invrgbl: the mask counts every
ray through a Gaussian's 3-sigma support, partly lit), received ratio 0.23
(path) / 0.17 (invrgbl).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from mi_invrgbl.cli import main
from mi_invrgbl.synthetic.writers import read_exr
import variant_choice

POSE_PX = 1.5
CHROMA_TOL = 0.02
CAST_RATIO = 0.6
RECEIVE_RATIO = 0.5
SUN_ELEVATION = 35.0
RADIUS = 0.8

SCENE = """<scene version="3.0.0">
  <default name="spp" value="16"/>
  %(integrator)s
  <sensor type="perspective" id="cam_a">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="16, -14, 7" target="8, 0, 0.5" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="96"/><integer name="height" value="64"/>
      <rfilter type="box"/></film>
  </sensor>
  <sensor type="perspective" id="cam_b">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="17, -13, 7" target="9, 0, 0.5" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="96"/><integer name="height" value="64"/>
      <rfilter type="box"/></film>
  </sensor>
  <emitter type="directional" id="sun">
    <vector name="direction" value="%(travel)s"/><rgb name="irradiance" value="3, 3, 3"/>
  </emitter>
  <emitter type="constant" id="sky"><rgb name="radiance" value="0.1, 0.1, 0.1"/></emitter>
  <shape type="rectangle" id="ground">
    <transform name="to_world"><scale value="20"/><translate x="8"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
  </shape>
  <shape type="cube" id="wall">
    <transform name="to_world"><scale x="0.2" y="12" z="3"/><translate z="3"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.45"/></bsdf>
  </shape>
</scene>
"""
# (The wall's BSDF differs from the ground's: Mitsuba merges meshes sharing one.)
SUN = np.array([-math.cos(math.radians(SUN_ELEVATION)), 0.0, math.sin(math.radians(SUN_ELEVATION))])
IN_SUN, IN_SHADOW = (13.0, 0.0, 0.0), (4.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    variant_choice.use()
    import mi_invrgbl  # noqa: F401
    import trimesh
    root = tmp_path_factory.mktemp("insert")
    travel = ", ".join("%.9g" % v for v in -SUN)
    (root / "path.xml").write_text(SCENE % {"integrator": '<integrator type="path">'
                                            '<integer name="max_depth" value="3"/></integrator>',
                                            "travel": travel})
    (root / "invrgbl.xml").write_text(SCENE % {"integrator": '<integrator type="invrgbl">'
                                               '<integer name="samples" value="16"/></integrator>',
                                               "travel": travel})
    trimesh.creation.icosphere(subdivisions=3, radius=RADIUS).export(str(root / "sphere.obj"))
    trimesh.creation.icosphere(subdivisions=3, radius=RADIUS).export(str(root / "sphere.ply"))
    (root / "broken.obj").write_text("v 0 0\nf 1 2 7\n")
    write_fitted_car(root / "fit")
    return root


def write_fitted_car(folder):
    """A 'fitted' scene with one dynamic node: a box of surface Gaussians, 2 x 1.2 x 1 m."""
    from mi_invrgbl.physics.gaussian_ply import GaussianCloud, matrix_to_quaternion, write_ply
    folder.mkdir()
    size, step = np.array([2.0, 1.2, 1.0]), 0.1
    centers, rots = [], []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        gu = (np.arange(int(size[u] / step)) + 0.5) * step - size[u] / 2
        gv = (np.arange(int(size[v] / step)) + 0.5) * step - size[v] / 2
        uu, vv = np.meshgrid(gu, gv, indexing="ij")
        for sign in (-1.0, 1.0):
            c = np.zeros((uu.size, 3))
            c[:, u], c[:, v], c[:, axis] = uu.ravel(), vv.ravel(), sign * size[axis] / 2
            n = np.zeros(3)
            n[axis] = sign
            x = np.zeros(3)
            x[u] = 1.0
            R = np.stack([x, np.cross(n, x), n], axis=1)
            centers.append(c)
            rots.append(np.repeat(R[None], len(c), axis=0))
    c = np.concatenate(centers)
    R = np.concatenate(rots)
    N = len(c)
    cloud = GaussianCloud(centers=c.astype(np.float32),
                          scales=np.tile(np.float32([0.07, 0.07, 0.005]), (N, 1)),
                          quaternions=matrix_to_quaternion(R).astype(np.float32),
                          opacities=np.full(N, 0.98, np.float32), normals=R[:, :, 2].astype(np.float32),
                          albedo=np.tile(np.float32([0.6, 0.6, 0.6]), (N, 1)),
                          roughness=np.full(N, 0.9, np.float32), lidar_albedo=np.full(N, 0.4, np.float32))
    write_ply(str(folder / "object_7.ply"), cloud)
    (folder / "scene.xml").write_text(
        '<scene version="3.0.0"><integrator type="invrgbl"/>'
        '<emitter type="shsun" id="sky"><string name="sh" value="3 3 3"/></emitter>'
        '<shape type="gaussians" id="object_7"><string name="filename" value="object_7.ply"/>'
        '<transform name="to_world"><translate x="30" y="2" z="0.5"/></transform></shape></scene>')


def run(args):
    assert main(args) == 0, args


def rgb(path):
    ch = read_exr(str(path))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def centre_rays(sensor):
    film = sensor.film()
    W, H = (int(v) for v in film.size())
    idx = dr.arange(mi.UInt32, W * H)
    pos = mi.Point2f((mi.Float(idx % W) + 0.5) / W, (mi.Float(idx // W) + 0.5) / H)
    rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    return rays, (H, W)


def hits(scene_xml, sensor_id="cam_a"):
    """Per pixel centre: the shape id hit (or '') and the hit position."""
    scene = mi.load_file(str(scene_xml))
    sensor = next(s for s in scene.sensors() if s.id() == sensor_id)
    rays, (H, W) = centre_rays(sensor)
    si = scene.ray_intersect(rays)
    ptr = np.array(dr.reinterpret_array(mi.UInt32, si.shape)).ravel()
    names = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]): s.id() for s in scene.shapes()}
    ids = np.array([names.get(int(p), "") for p in ptr]).reshape(H, W)
    p = np.array(si.p, np.float64).reshape(3, -1).T.reshape(H, W, 3)
    return scene, sensor, ids, p


def project(sensor, point):
    """Pixel (col, row) of a world point in a Mitsuba perspective camera (fov along x)."""
    m = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    x, y, z, _ = np.linalg.inv(m) @ np.append(point, 1.0)
    W, H = (int(v) for v in sensor.film().size())
    f = (W / 2) / math.tan(math.radians(60) / 2)
    return W / 2 - f * x / z, H / 2 - f * y / z   # camera +x is image left, +y is up


def sun_blocked_by(scene, points, shape_id):
    """Whether the sun ray from each point first hits ``shape_id``."""
    pts = points.reshape(-1, 3) + 1e-3 * np.array([0, 0, 1.0])
    rays = mi.Ray3f(mi.Point3f(*[pts[:, k].astype(np.float32) for k in range(3)]),
                    mi.Vector3f(*[np.full(len(pts), v, np.float32) for v in SUN]))
    si = scene.ray_intersect(rays)
    target = next(s for s in scene.shapes() if s.id() == shape_id)
    ptr = np.array(dr.reinterpret_array(mi.UInt32, si.shape)).ravel()
    return (ptr == int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(target))[0])).reshape(points.shape[:2])


def lum(img):
    return img @ np.array([0.2126, 0.7152, 0.0722])


@pytest.mark.parametrize("kind", ["mesh", "gaussians"])
def test_object_at_its_pose_casts_and_receives_shadows(files, tmp_path, kind):
    target = files / ("path.xml" if kind == "mesh" else "invrgbl.xml")
    obj = str(files / "sphere.obj") if kind == "mesh" else str(files / "fit" / "scene.xml") + ":object_7"
    extra = ["--albedo", "0.7,0.7,0.7"] if kind == "mesh" else ["--spp", "4"]
    sun_out, shade_out = tmp_path / "sun", tmp_path / "shade"
    run(["insert", str(target), "--object", obj, "--pose", "%g,%g,%g,30" % IN_SUN, "-o", str(sun_out),
         "--frames", "0"] + extra)
    run(["insert", str(target), "--object", obj, "--pose", "%g,%g,%g,30" % IN_SHADOW,
         "-o", str(shade_out), "--frames", "0"] + extra)

    # Pose: the object's pixels are centred on its centre's projection.
    scene, sensor, ids, p = hits(sun_out / "scene.xml")
    mask = ids == "inserted"
    rows, cols = np.nonzero(mask)
    centre = np.array(IN_SUN) + [0, 0, RADIUS if kind == "mesh" else 0.5]
    u, v = project(sensor, centre)
    err = math.hypot(cols.mean() + 0.5 - u, rows.mean() + 0.5 - v)
    print("%s: %d object pixels, centroid %.2f px from the projected centre" % (kind, mask.sum(), err))
    assert mask.sum() > 20 and err < POSE_PX

    # Cast: ground pixels whose sun ray the object blocks get darker.
    without = tmp_path / "without"
    run(["relight", str(target), "-o", str(without), "--frames", "0", "--sky-scale", "1"]
        + (["--spp", "4"] if kind == "gaussians" else []))   # the same lighting, as shsun
    cast = (ids == "ground") & sun_blocked_by(scene, p, "inserted")
    with_obj, no_obj = lum(rgb(sun_out / "frame_0000.exr")), lum(rgb(without / "frame_0000.exr"))
    cast_ratio = with_obj[cast].mean() / no_obj[cast].mean()

    # Receive: the same object in the wall's shadow is darker than in the sun.
    _, _, ids_shade, _ = hits(shade_out / "scene.xml")
    in_sun = with_obj[mask].mean()
    in_shade = lum(rgb(shade_out / "frame_0000.exr"))[ids_shade == "inserted"].mean()
    print("%s: cast shadow %d px, ground radiance ratio %.3f; object in shade / in sun %.3f"
          % (kind, cast.sum(), cast_ratio, in_shade / in_sun))
    assert cast.sum() > 10 and cast_ratio < CAST_RATIO
    assert in_shade / in_sun < RECEIVE_RATIO


def test_colour_follows_the_target_light(files, tmp_path):
    chroma = {}
    for name, light, expected in [
            ("warm", ["--sun-irradiance", "3,2,1", "--sky-radiance", "0"], [3, 2, 1]),
            ("blue", ["--sun-irradiance", "0", "--sky-radiance", "0.2,0.3,0.6"], [0.2, 0.3, 0.6])]:
        lit = tmp_path / ("scene_" + name)
        run(["relight", str(files / "path.xml"), "-o", str(lit), "--frames", "0", "--spp", "1"] + light)
        out = tmp_path / name
        run(["insert", str(lit / "scene.xml"), "--object", str(files / "sphere.ply"), "--pose",
             "%g,%g,%g" % IN_SUN, "--albedo", "0.6", "-o", str(out), "--frames", "0", "--spp", "32"])
        _, _, ids, _ = hits(out / "scene.xml")
        colour = rgb(out / "frame_0000.exr")[ids == "inserted"].mean(axis=0)
        chroma[name] = colour / colour.sum()
        want = np.array(expected, np.float64) / np.sum(expected)
        print("%s light: object chromaticity %s, light %s" % (name, np.round(chroma[name], 4),
                                                               np.round(want, 4)))
        assert chroma[name] == pytest.approx(want, abs=CHROMA_TOL)
    assert np.abs(chroma["warm"] - chroma["blue"]).max() > 0.2


@pytest.mark.parametrize("kind", ["mesh", "gaussians"])
def test_track_moves_the_object_per_frame(files, tmp_path, kind):
    track = tmp_path / "track.json"
    poses = [[10.0, -1.0, 0.0, 0.0], [12.0, 2.0, 0.0, 90.0]]
    track.write_text(json.dumps(poses))
    out = tmp_path / "track"
    # The sphere's centre is RADIUS above its bottom centre, the fitted box's 0.5 m.
    obj, lift = ((str(files / "sphere.obj"), RADIUS) if kind == "mesh" else
                 (str(files / "fit" / "scene.xml") + ":object_7", 0.5))
    run(["insert", str(files / "path.xml"), "--object", obj, "--track", str(track),
         "-o", str(out), "--spp", "2", "--samples", "2"])
    assert (out / "frame_0000.png").is_file() and (out / "frame_0001.png").is_file()
    # Frame 1 (camera cam_b) must show the sphere at the second pose.
    scene = mi.load_file(str(out / "scene.xml"))
    from mi_invrgbl.apps.frame_set import FrameSet
    from mi_invrgbl.apps.insert import TrackHook
    from mi_invrgbl.apps.pose_input import pose_from_values
    frames = FrameSet(str(files / "path.xml"), scene)
    hook = TrackHook("inserted", [pose_from_values(p) for p in poses], pose_from_values(poses[0]))
    for frame in frames.all:
        sensor = frames.apply(scene, frame)
        hook(scene, frame, sensor)
        rays, (H, W) = centre_rays(sensor)
        si = scene.ray_intersect(rays)
        target = next(s for s in scene.shapes() if s.id() == "inserted")
        hit = np.array(dr.reinterpret_array(mi.UInt32, si.shape)).ravel() == \
            int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(target))[0])
        rows, cols = np.nonzero(hit.reshape(H, W))
        u, v = project(sensor, np.array(poses[frame.index][:3]) + [0, 0, lift])
        assert math.hypot(cols.mean() + 0.5 - u, rows.mean() + 0.5 - v) < POSE_PX


def test_edit_is_visible_as_xml(files, tmp_path):
    out = tmp_path / "o"
    run(["insert", str(files / "invrgbl.xml"), "--object", str(files / "fit" / "scene.xml") + ":object_7",
         "--pose", "10,0,0", "-o", str(out), "--frames", "0", "--spp", "1", "--samples", "2"])
    diff = (out / "scene.diff").read_text()
    assert '+    <shape type="gaussians" id="inserted">' in diff
    assert "object_7.ply" in diff and "translate" not in diff    # OTHER's frame-0 pose is dropped


def test_gaussians_switch_a_path_scene_to_invrgbl(files, tmp_path, capsys):
    out = tmp_path / "o"
    run(["insert", str(files / "path.xml"), "--object", str(files / "fit" / "scene.xml") + ":object_7",
         "--pose", "10,0,0", "-o", str(out), "--frames", "0", "--spp", "1", "--samples", "2"])
    assert "now uses 'invrgbl'" in capsys.readouterr().out
    assert 'integrator type="invrgbl"' in (out / "scene.xml").read_text()


def test_stored_sun_visibility_is_traced_after_insertion(files, tmp_path):
    # A fit writes sun_visibility="attribute" (its learned v_sun); the
    # background's stored values know nothing of the new object, whose
    # shadow appears only if the sun is traced.
    stored = tmp_path / "stored.xml"
    stored.write_text((files / "invrgbl.xml").read_text().replace(
        '<integer name="samples" value="16"/>',
        '<integer name="samples" value="16"/><string name="sun_visibility" value="attribute"/>'))
    out = tmp_path / "o"
    run(["insert", str(stored), "--object", str(files / "fit" / "scene.xml") + ":object_7",
         "--pose", "10,0,0", "-o", str(out), "--frames", "0", "--spp", "1", "--samples", "2"])
    text = (out / "scene.xml").read_text()
    assert 'name="sun_visibility" value="trace"' in text and '"attribute"' not in text


@pytest.mark.parametrize("args, message", [
    (["--object", "FIT:object_9", "--pose", "10,0,0"], "no shape node 'object_9' (its nodes: object_7)"),
    (["--object", "FIT", "--pose", "10,0,0"], "name the node to take from it"),
    (["--object", "SPHERE", "--pose", "500,0,0"], "lies outside the scene"),
    (["--object", "SPHERE", "--pose", "1,2"], "expected x,y,z"),
    (["--object", "BROKEN", "--pose", "10,0,0"], "cannot load the mesh"),
    (["--object", "/nonexistent/car.obj", "--pose", "10,0,0"], "not found"),
    (["--object", "SPHERE", "--track", "SHORT"], "--track has 1 poses but frame 1 is rendered"),
])
def test_bad_input_gives_one_clear_error(files, tmp_path, capsys, args, message):
    short = tmp_path / "short.json"
    short.write_text("[[10, 0, 0, 0]]")
    subst = {"FIT": str(files / "fit" / "scene.xml"), "SPHERE": str(files / "sphere.obj"),
             "BROKEN": str(files / "broken.obj"), "SHORT": str(short)}
    args = [subst.get(a.split(":")[0], a.split(":")[0]) + (":" + a.split(":")[1] if ":" in a else "")
            for a in args]
    code = main(["insert", str(files / "path.xml"), "-o", str(tmp_path / "o"), "--spp", "1"] + args)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
