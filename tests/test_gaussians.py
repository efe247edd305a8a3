"""The ``gaussians`` shape and its 3DGS-style PLY I/O.

References are computed here with numpy (quaternion maths, sigmoid/log,
sRGB decoding), never through the plugin's own helpers, so a convention
slip in the plugin makes these tests fail.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from mi_invrgbl.physics import gaussian_ply as gp

SH_C0 = 0.28209479177387814


# ----------------------------------------------------------------- helpers

def random_cloud(n=7, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    f = np.float32
    return gp.GaussianCloud(
        centers=rng.uniform(-3, 3, (n, 3)).astype(f),
        scales=rng.uniform(0.01, 0.5, (n, 3)).astype(f),
        quaternions=q.astype(f),
        opacities=rng.uniform(0.05, 0.95, n).astype(f),
        normals=normals.astype(f),
        albedo=rng.uniform(0.05, 0.95, (n, 3)).astype(f),
        roughness=rng.uniform(0.05, 1.0, n).astype(f),
        lidar_albedo=rng.uniform(0.0, 1.0, n).astype(f),
        sun_visibility=rng.uniform(0.0, 1.0, n).astype(f))


def write_raw_ply(path, columns):
    """Binary little-endian PLY with the given {name: (N,) array} columns, in order."""
    n = len(next(iter(columns.values())))
    table = np.empty(n, dtype=[(k, "<f4") for k in columns])
    for k, v in columns.items():
        table[k] = v
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join("property float %s\n" % k for k in columns) + "end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(table.tobytes())


def read_raw_ply(path):
    with open(path, "rb") as f:
        names = []
        while True:
            line = f.readline().decode("ascii").split()
            if line[0] == "property":
                names.append(line[2])
            if line[0] == "end_header":
                break
        data = np.frombuffer(f.read(), dtype=[(k, "<f4") for k in names])
    return names, data


def quat_wxyz_to_matrix(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def params_of(shape):
    p = mi.traverse(shape)
    data = np.array(p["data"]).reshape(-1, 10)
    return p, data


def same_rotation(q_wxyz_a, q_wxyz_b, atol=1e-5):
    """Quaternions q and -q are the same rotation."""
    a = np.asarray(q_wxyz_a, np.float64)
    b = np.asarray(q_wxyz_b, np.float64)
    return np.allclose(a, b, atol=atol) or np.allclose(a, -b, atol=atol)


def first_hits(scene, origins, direction):
    o = np.asarray(origins, np.float32)
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*np.broadcast_to(np.float32(direction), o.shape).T))
    return np.array(scene.ray_intersect_preliminary(ray).is_valid())


def load_error(d):
    with pytest.raises(Exception) as info:
        mi.load_dict(d)
    return str(info.value)


# ------------------------------------------------------------- round trips

def test_filename_loads_through_mitsuba(tmp_path):
    # Regression: the resolved path (mi.filesystem.path) used to reach
    # os.fspath(), which raised TypeError, so no PLY file could be loaded.
    cloud = random_cloud(3)
    gp.write_ply(str(tmp_path / "c.ply"), cloud)
    shape = mi.load_dict({"type": "gaussians", "filename": str(tmp_path / "c.ply")})
    assert dr.width(mi.traverse(shape)["opacities"]) == 3


def test_ply_round_trip_all_fields(tmp_path):
    cloud = random_cloud()
    ref = {k: np.array(getattr(cloud, k)) for k in
           ("centers", "scales", "quaternions", "opacities", "normals", "albedo",
            "roughness", "lidar_albedo", "sun_visibility")}
    path = str(tmp_path / "cloud.ply")
    gp.write_ply(path, cloud)

    # The file itself: 3DGS conventions (log scales, logit opacity, w first).
    names, raw = read_raw_ply(path)
    assert names[:6] == ["x", "y", "z", "nx", "ny", "nz"]
    assert names[-7:] == ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert np.allclose(np.exp(np.stack([raw["scale_%d" % i] for i in range(3)], 1)), ref["scales"], rtol=1e-5)
    assert np.allclose(1 / (1 + np.exp(-raw["opacity"])), ref["opacities"], atol=1e-6)
    assert np.allclose(np.stack([raw["rot_%d" % i] for i in range(4)], 1), ref["quaternions"], atol=1e-7)

    back = gp.read_ply(path)
    for name, value in ref.items():
        assert np.allclose(getattr(back, name), value, rtol=1e-5, atol=1e-6), name

    # Inside the shape, 'data' holds centre, scale, quaternion x y z w.
    shape = mi.load_dict({"type": "gaussians", "id": "g", "filename": path})
    p, data = params_of(shape)
    assert np.allclose(data[:, 0:3], ref["centers"], atol=1e-6)
    assert np.allclose(data[:, 3:6], ref["scales"], rtol=1e-5)
    for q_xyzw, q in zip(data[:, 6:10], ref["quaternions"]):
        assert same_rotation(np.r_[q_xyzw[3], q_xyzw[:3]], q)
    assert np.allclose(np.array(p["opacities"]).ravel(), ref["opacities"], atol=1e-6)
    assert np.allclose(np.array(p["lidar_albedo"]).ravel(), ref["lidar_albedo"], atol=1e-6)
    assert np.allclose(np.array(p["roughness"]).ravel(), ref["roughness"], atol=1e-6)
    assert np.allclose(np.array(p["albedo"]).reshape(-1, 3), ref["albedo"], atol=1e-6)
    assert np.allclose(np.array(p["sun_visibility"]).ravel(), ref["sun_visibility"], atol=1e-6)
    assert np.allclose(np.array(p["normal"]).reshape(-1, 3), ref["normals"], atol=1e-6)


def test_quaternion_convention_by_ray_hits(tmp_path):
    # One elongated Gaussian (long axis local x) rotated 90 degrees about z,
    # written w-first: its long axis must lie along world y. Read as x-first
    # the same numbers would be a 90-degree turn about x (long axis still x).
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    cloud = gp.GaussianCloud(centers=np.zeros((1, 3), np.float32),
                             scales=np.float32([[1.0, 0.05, 0.05]]),
                             quaternions=np.float32([[c, 0, 0, s]]),
                             opacities=np.float32([0.9]))
    path = str(tmp_path / "rot.ply")
    gp.write_ply(path, cloud)
    scene = mi.load_dict({"type": "scene", "g": {"type": "gaussians", "filename": path}})
    down = [0, 0, -1]
    along_y = first_hits(scene, [[0, 1.5, 5], [0, -1.5, 5], [0, 2.5, 5]], down)
    along_x = first_hits(scene, [[1.5, 0, 5], [-1.5, 0, 5]], down)
    assert list(along_y) == [True, True, True]   # extent 3 sigma = 3 m along y
    assert not along_x.any()


def test_mitsuba_ellipsoids_reads_our_file(tmp_path):
    cloud = random_cloud(5, seed=3)
    path = str(tmp_path / "ours.ply")
    gp.write_ply(path, cloud)
    stock = mi.load_dict({"type": "ellipsoids", "filename": path})
    data = np.array(mi.traverse(stock)["data"]).reshape(-1, 10)
    assert np.allclose(data[:, :3], cloud.centers, atol=1e-6)
    assert np.allclose(data[:, 3:6], cloud.scales, rtol=1e-5)
    for q_xyzw, q in zip(data[:, 6:10], cloud.quaternions):
        assert same_rotation(np.r_[q_xyzw[3], q_xyzw[:3]], q)


@pytest.mark.parametrize("with_normals", [False, True])
def test_plain_3dgs_ply_defaults(tmp_path, with_normals):
    rng = np.random.default_rng(5)
    n = 6
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales = rng.uniform(0.02, 0.4, (n, 3))
    f_dc = rng.uniform(-1.5, 1.5, (n, 3))
    cols = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n)}
    if with_normals:  # 3DGS writes zeros here: they mean "no normal"
        cols.update({"nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)})
    cols.update({"f_dc_%d" % i: f_dc[:, i] for i in range(3)})
    cols.update({"f_rest_%d" % i: rng.normal(size=n) for i in range(9)})
    logit = rng.normal(size=n)
    cols["opacity"] = logit
    cols.update({"scale_%d" % i: np.log(scales[:, i]) for i in range(3)})
    cols.update({"rot_%d" % i: q[:, i] for i in range(4)})
    path = str(tmp_path / "plain.ply")
    write_raw_ply(path, cols)

    shape = mi.load_dict({"type": "gaussians", "id": "g", "filename": path})
    p, data = params_of(shape)
    # Documented defaults: albedo = DC colour (sRGB -> linear), roughness 0.5,
    # LiDAR albedo = luminance of the albedo, sun visibility 1, normal =
    # shortest axis, opacity = sigmoid(logit).
    srgb = np.clip(0.5 + SH_C0 * f_dc, 0, 1)
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    assert np.allclose(np.array(p["albedo"]).reshape(n, 3), lin, atol=1e-5)
    assert np.allclose(np.array(p["roughness"]).ravel(), 0.5)
    lum = lin @ np.array([0.2126, 0.7152, 0.0722])
    assert np.allclose(np.array(p["lidar_albedo"]).ravel(), lum, atol=1e-5)
    assert np.allclose(np.array(p["sun_visibility"]).ravel(), 1.0)
    assert np.allclose(np.array(p["opacities"]).ravel(), 1 / (1 + np.exp(-logit)), atol=1e-5)
    normals = np.array(p["normal"]).reshape(n, 3)
    for i in range(n):
        axis = quat_wxyz_to_matrix(q[i])[:, np.argmin(scales[i])]
        assert abs(abs(np.dot(normals[i], axis)) - 1) < 1e-5
    assert np.allclose(data[:, 3:6], scales, rtol=1e-5)


def test_to_world_is_applied(tmp_path):
    cloud = random_cloud(4, seed=7)
    path = str(tmp_path / "c.ply")
    gp.write_ply(path, cloud)
    angle, k, t = 37.0, 2.5, np.array([1.0, -2.0, 0.5])
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])  # rotate() wants a unit axis
    to_world = mi.ScalarTransform4f().translate(t.tolist()).rotate(axis.tolist(), angle).scale(k)
    shape = mi.load_dict({"type": "gaussians", "id": "g", "filename": path, "to_world": to_world})
    p, data = params_of(shape)
    # Rodrigues rotation, written out here.
    u = axis / np.linalg.norm(axis)
    a = np.deg2rad(angle)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    assert np.allclose(data[:, :3], cloud.centers @ (k * R).T + t, atol=1e-4)
    assert np.allclose(data[:, 3:6], cloud.scales * k, rtol=1e-5)
    for q_xyzw, q in zip(data[:, 6:10], cloud.quaternions):
        got = quat_wxyz_to_matrix(np.r_[q_xyzw[3], q_xyzw[:3]])
        assert np.allclose(got, R @ quat_wxyz_to_matrix(q), atol=1e-5)
    assert np.allclose(np.array(p["normal"]).reshape(-1, 3), cloud.normals @ R.T, atol=1e-5)


# -------------------------------------------------------------- bad inputs

def test_nan_field_in_file_is_refused(tmp_path):
    cloud = random_cloud(4)
    cloud.lidar_albedo[2] = np.nan
    path = str(tmp_path / "nan.ply")
    gp.write_ply(path, cloud)
    msg = load_error({"type": "gaussians", "filename": path})
    assert "nan.ply" in msg and "lidar_albedo" in msg and "index 2" in msg


def test_nan_in_tensor_parameter_is_refused():
    c = np.zeros((3, 3), np.float32)
    c[1, 2] = np.nan
    msg = load_error({"type": "gaussians", "id": "bad", "centers": mi.TensorXf(c)})
    assert "'bad'" in msg and "centers" in msg


def test_truncated_file_is_refused(tmp_path):
    path = tmp_path / "cut.ply"
    gp.write_ply(str(path), random_cloud(5))
    raw = path.read_bytes()
    path.write_bytes(raw[:-10])
    msg = load_error({"type": "gaussians", "filename": str(path)})
    assert "cut.ply" in msg and "truncated" in msg


def test_missing_file_is_refused(tmp_path):
    msg = load_error({"type": "gaussians", "filename": str(tmp_path / "nowhere.ply")})
    assert "nowhere.ply" in msg and "not found" in msg


def test_zero_quaternion_is_refused(tmp_path):
    cloud = random_cloud(3)
    cloud.quaternions[1] = 0
    path = str(tmp_path / "zq.ply")
    gp.write_ply(path, cloud)
    msg = load_error({"type": "gaussians", "filename": path})
    assert "zq.ply" in msg and "quaternion" in msg


def test_shear_in_to_world_is_refused(tmp_path):
    path = str(tmp_path / "c.ply")
    gp.write_ply(path, random_cloud(2))
    shear = mi.ScalarTransform4f(np.array([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                                          np.float32))
    msg = load_error({"type": "gaussians", "filename": path, "to_world": shear})
    assert "c.ply" in msg and "to_world" in msg
    # Non-uniform scale is a shear of the Gaussians' frames too.
    msg = load_error({"type": "gaussians", "filename": path,
                      "to_world": mi.ScalarTransform4f().scale([1, 2, 1])})
    assert "to_world" in msg


# ---------------------------------------------------- degenerate Gaussians

def lidar_scene(gaussians, height=2.0, n_rays=16, tmp_path=None):
    rng = np.random.default_rng(11)
    th = rng.uniform(0, 0.6, n_rays)
    ph = rng.uniform(0, 2 * np.pi, n_rays)
    rays = np.zeros((n_rays, 6))
    rays[:, 3:] = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)], 1)
    np.save(tmp_path / "rays.npy", rays)
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "lidar_return"},
        "sensor": {"type": "lidar", "rays": str(tmp_path / "rays.npy"),
                   "to_world": mi.ScalarTransform4f().translate([0, 0, height])},
        "g": gaussians})


def tensor_gaussians(centers, scales, opacities):
    n = len(centers)
    return {"type": "gaussians", "centers": mi.TensorXf(np.float32(centers)),
            "scales": mi.TensorXf(np.float32(scales).reshape(n, 3)),
            "opacities": mi.TensorXf(np.float32(opacities).reshape(n))}


@pytest.mark.parametrize("scale", [0.0, 1e4])
def test_extreme_scales_render_finite(tmp_path, scale):
    g = tensor_gaussians([[0, 0, 0], [0.3, 0, 0]], [[scale, scale, scale], [scale, 0, scale]], [0.8, 0.8])
    img = np.array(mi.render(lidar_scene(g, tmp_path=tmp_path)))
    assert np.all(np.isfinite(img))
    if scale == 0.0:  # a zero-size Gaussian is (almost) never hit
        assert img[..., 2].sum() == 0
    else:             # the sensor sits inside a 1e4 m Gaussian: the design says
        # a ray that starts inside a Gaussian never sees it -> no return.
        assert img[..., 4].max() <= 1.0


def test_zero_opacity_is_empty(tmp_path):
    xs = np.linspace(-1, 1, 11)
    X, Y = np.meshgrid(xs, xs)
    c = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    g = tensor_gaussians(c, np.tile([0.2, 0.2, 0.02], (len(c), 1)), np.zeros(len(c)))
    img = np.array(mi.render(lidar_scene(g, tmp_path=tmp_path)))
    assert np.all(img == 0)
