r"""The ``lidar`` sensor: a spinning LiDAR as a Mitsuba sensor.

.. _sensor-lidar:

Spinning LiDAR (:monosp:`lidar`)
--------------------------------

.. pluginparameters::

 * - to_world
   - |transform|
   - Sensor pose. The local frame is the datasets' one: x forward, y left,
     z up (the spin axis). (Default: identity)

 * - preset
   - |string|
   - Elevation table of a common sensor: ``hdl64`` (64 beams, +2 to -24.9
     degrees, linear), ``vlp32`` (VLP-32C, its documented non-uniform table of
     32 beams from +15 to -25 degrees) or ``vlp16`` (16 beams, +15 to -15
     degrees every 2 degrees). (Default: none)

 * - elevations
   - |string|
   - Comma-separated beam elevations in degrees, one per beam, top first. Their
     count is the film height. (Default: none)

 * - fov_up, fov_down
   - |float|
   - Elevation of the top and of the bottom beam in degrees; the film's rows
     are spread linearly between them (both end points included). Used when
     neither ``preset``, ``elevations`` nor ``rays`` is given.
     (Default: 2.0 and -24.9, an HDL-64E)

 * - rays
   - |string|
   - Path to a ``.npy`` array of shape (N, 6): ray origins (3) and directions
     (3) in the sensor frame (a relative path is resolved against the scene's
     folder), for scan patterns that are not a grid; or (N, 7)
     whose last column is each ray's beam. The film is then N x 1 and pixel
     ``i`` is ray ``i``. Without the beam column, a ray's beam is found from
     its elevation (rows of the pattern; a pattern without rows is one beam,
     see :mod:`mi_invrgbl.physics.beam_layout`). (Default: none)

 * - near_clip
   - |float|
   - Minimum range in metres: LiDARs report no closer returns. Every ray starts
     ``near_clip`` along its beam, so surfaces closer than that are not hit by
     the sensor ray. (Default: 0.5)

 * - far_clip
   - |float|
   - Maximum range in metres; rays end there (``maxt = far_clip - near_clip``
     from the shifted origin). (Default: 120)

 * - film
   - |film|
   - Its width is the number of azimuth steps, its height the number of beams.
     (Default: ``hdrfilm`` 1024 x beams (64 for the ``fov`` mode), box filter)

Pixel ``(row, col)`` is one exact beam: row 0 is the highest elevation,
column ``col`` has azimuth ``phi = pi (1 - 2 (col + 0.5) / W)``, i.e. column
``W/2`` looks (almost exactly) along +x, azimuth grows to the left (+y) and
column 0 looks backwards via the left side. This is the common range-image
projection ``u = 0.5 (1 - atan2(y, x) / pi) W`` with pixel centres at
``u = col + 0.5``. The direction of a beam with elevation ``e`` is
``(cos e cos phi, cos e sin phi, sin e)``.

The sub-pixel position of a sample is ignored: all samples of a pixel are the
same ray, so one sample per pixel is exact and a ``box`` filter (the default)
keeps each beam's value in its own pixel. Other filters blend neighbouring
beams.

Near clipping: Mitsuba 3 rays have no ``mint``, so, as Mitsuba's own cameras
do, the sensor moves the ray origin ``near_clip`` forward along the beam. A
surface closer than ``near_clip`` is therefore not seen by the sensor ray.
With the ``laser`` emitter and a stock integrator such a surface still blocks
the shadow ray back to the laser, so a beam through it returns nothing, as on
a real sensor. Integrators that trace the sensor's rays themselves measure the
range as ``near_clip + t``, or use :py:meth:`all_rays` with ``clip=False``
(origin at the sensor, ``maxt = far_clip``) and drop returns closer than
:py:attr:`near_clip` themselves.

Beams: every pixel belongs to a beam (:py:meth:`beam_index`), which is what a
per-beam quantity (a gain, a ray-drop rate) must be indexed by: the film row
of a spinning sensor, the ray's own beam in ``rays`` mode, whose film has a
single row.

Python helpers for integrators: :py:meth:`beam_grid`, :py:meth:`beam_index`,
:py:meth:`beam_at`, :py:attr:`n_beams`,
:py:meth:`ray_directions_local`, :py:meth:`all_rays`, :py:meth:`origin`,
:py:attr:`near_clip`, :py:attr:`far_clip`, :py:attr:`width`,
:py:attr:`height`.

.. tabs::

    .. code-tab:: python

        'type': 'lidar',
        'preset': 'vlp16',
        'to_world': mi.ScalarTransform4f().translate([0, 0, 1.7]),
        'film': {'type': 'hdrfilm', 'width': 1800, 'height': 16,
                 'rfilter': {'type': 'box'}},
"""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics.host_arrays import jit_array

_variant = mi.variant()

#: Default number of azimuth steps when no film is given.
DEFAULT_WIDTH = 1024
#: Default beam count of the ``fov_up``/``fov_down`` mode (an HDL-64E).
DEFAULT_BEAMS = 64

# VLP-32C vertical angles from its user manual, sorted top first: finely spaced
# (1/3 degree) around the horizon where the targets of a car are.
_VLP32C = (15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667,
           0.333, 0.0, -0.333, -0.667, -1.0, -1.333, -1.667, -2.0, -2.333,
           -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148, -7.254,
           -8.843, -11.31, -15.639, -25.0)

#: Elevation tables in degrees, top beam first.
PRESETS = {
    # Nominal HDL-64E: 64 beams spread over its +2..-24.9 degree field of view.
    # Individual units differ slightly; pass their calibration as `elevations`.
    "hdl64": tuple(np.linspace(2.0, -24.9, 64)),
    "vlp32": _VLP32C,
    "vlp16": tuple(float(e) for e in range(15, -16, -2)),
}


class LidarError(ValueError):
    """An invalid ``lidar`` parameter; the message names it."""


def _float_prop(props, name, default):
    value = float(props.get(name, default))
    if not np.isfinite(value):
        raise LidarError("lidar: parameter '%s' must be finite, got %r" % (name, value))
    return value


def _parse_elevations(text: str) -> np.ndarray:
    try:
        values = [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
    except ValueError:
        raise LidarError("lidar: parameter 'elevations' must be comma-separated "
                         "degrees, got %r" % text) from None
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        raise LidarError("lidar: parameter 'elevations' lists no beam")
    if not np.all(np.isfinite(values)) or np.any(np.abs(values) > 90.0):
        raise LidarError("lidar: parameter 'elevations' must hold finite angles "
                         "within [-90, 90] degrees, got %r" % text)
    return values


def _load_rays(path: str) -> np.ndarray:
    import os
    if not os.path.isabs(path):
        # Relative to the scene's folder (on the file resolver while a scene
        # file loads), as Mitsuba resolves its own file names.
        path = str(mi.file_resolver().resolve(path))
    try:
        rays = np.load(path)
    except Exception as exc:
        raise LidarError("lidar: parameter 'rays' could not read %r (%s)" % (path, exc)) from None
    rays = np.asarray(rays, dtype=np.float64)
    if rays.ndim != 2 or rays.shape[1] not in (6, 7) or rays.shape[0] == 0:
        raise LidarError("lidar: parameter 'rays' must be a non-empty (N, 6) array "
                         "of origins and directions (or (N, 7) with each ray's beam), "
                         "got shape %s" % (rays.shape,))
    if not np.all(np.isfinite(rays)):
        raise LidarError("lidar: parameter 'rays' contains NaN or Inf")
    norms = np.linalg.norm(rays[:, 3:6], axis=1)
    if np.any(norms < 1e-12):
        raise LidarError("lidar: parameter 'rays' has a zero direction (row %d)"
                         % int(np.argmin(norms)))
    if rays.shape[1] == 7 and (np.any(rays[:, 6] < 0) or np.any(rays[:, 6] != np.round(rays[:, 6]))):
        raise LidarError("lidar: parameter 'rays': column 7 (beam) must hold "
                         "non-negative integers")
    rays[:, 3:6] /= norms[:, None]
    return rays


def _given_film(props):
    for _, obj in props.objects(False):
        if isinstance(obj, mi.Film):
            return obj
    return None


def _check_transform(matrix, name):
    m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(m)):
        raise LidarError("lidar: parameter '%s' contains NaN or Inf:\n%s" % (name, m))


class LidarSensor(mi.Sensor):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        # Work out the scan pattern first: without a user film, it sets the
        # size of the default one, which must exist before mi.Sensor's
        # constructor (that would otherwise make a 768 x 576 Gaussian-filtered film).
        modes = [n for n in ("preset", "elevations", "rays") if n in props]
        if len(modes) > 1:
            raise LidarError("lidar: give only one of 'preset', 'elevations' and "
                             "'rays' (got %s)" % ", ".join(modes))
        self._rays_local = None       # (N, 6) in the explicit-ray mode
        self._elevations_deg = None   # (H,) in the grid modes with a table
        self._ray_beam = None         # (N,) beam of each ray in the explicit-ray mode
        fov = None
        if "preset" in props:
            name = str(props.get("preset")).lower()
            if name not in PRESETS:
                raise LidarError("lidar: parameter 'preset' must be one of %s, got %r"
                                 % (", ".join(sorted(PRESETS)), name))
            self._elevations_deg = np.asarray(PRESETS[name], dtype=np.float64)
        elif "elevations" in props:
            self._elevations_deg = _parse_elevations(str(props.get("elevations")))
        elif "rays" in props:
            rays = _load_rays(str(props.get("rays")))
            if rays.shape[1] == 7:
                self._ray_beam = rays[:, 6].astype(np.int64)
            else:
                from ..physics.beam_layout import ray_beams
                self._ray_beam = ray_beams(rays[:, 3:6])[0]
            self._rays_local = rays[:, :6]
        else:
            fov = (_float_prop(props, "fov_up", 2.0), _float_prop(props, "fov_down", -24.9))
            if not (-90.0 <= fov[1] <= fov[0] <= 90.0):
                raise LidarError("lidar: parameters 'fov_up' (%g) and 'fov_down' (%g) "
                                 "must satisfy -90 <= fov_down <= fov_up <= 90" % fov)

        film = _given_film(props)
        if film is None:
            if self._rays_local is not None:
                size = (self._rays_local.shape[0], 1)
            elif self._elevations_deg is not None:
                size = (DEFAULT_WIDTH, self._elevations_deg.size)
            else:
                size = (DEFAULT_WIDTH, DEFAULT_BEAMS)
            props["film"] = mi.load_dict({"type": "hdrfilm", "width": size[0],
                                          "height": size[1], "rfilter": {"type": "box"}})

        self._near = _float_prop(props, "near_clip", 0.5)
        self._far = _float_prop(props, "far_clip", 120.0)
        super().__init__(props)

        width, height = (int(v) for v in self.film().size())
        if width == 0 or height == 0:
            raise LidarError("lidar: parameter 'film' has zero size (%d x %d)" % (width, height))
        if self._rays_local is not None and (width, height) != (self._rays_local.shape[0], 1):
            raise LidarError("lidar: parameter 'film' must be %d x 1 for the %d rays "
                             "of 'rays', got %d x %d" % (self._rays_local.shape[0],
                                                         self._rays_local.shape[0], width, height))
        if self._elevations_deg is not None and height != self._elevations_deg.size:
            raise LidarError("lidar: parameter 'film' has height %d but the elevation "
                             "table has %d beams" % (height, self._elevations_deg.size))
        if fov is not None:
            self._elevations_deg = (np.linspace(fov[0], fov[1], height) if height > 1
                                    else np.array([0.5 * (fov[0] + fov[1])]))
        self._width, self._height = width, height
        self._build_tables()
        self._validate()

    # ------------------------------------------------------------------ set-up

    def _build_tables(self):
        dirs = self.ray_directions_local().reshape(-1, 3)
        self._dirs = mi.Vector3f(*(jit_array(mi.Float, dirs[:, k]) for k in range(3)))
        if self._rays_local is None:
            beam = np.repeat(np.arange(self._height), self._width)
        else:
            beam = self._ray_beam
        self._beams = jit_array(mi.UInt32, beam.astype(np.uint32))
        self._n_beams = int(beam.max()) + 1
        if self._rays_local is None:
            self._origins = None
        else:
            o = self._rays_local[:, :3]
            self._origins = mi.Point3f(*(jit_array(mi.Float, o[:, k]) for k in range(3)))

    def _validate(self):
        if not (self._near >= 0.0):
            raise LidarError("lidar: parameter 'near_clip' must be >= 0, got %g" % self._near)
        if not (self._far > self._near):
            raise LidarError("lidar: parameter 'far_clip' (%g) must exceed 'near_clip' (%g)"
                             % (self._far, self._near))
        _check_transform(self.m_to_world.matrix.numpy(), "to_world")

    def traverse(self, callback):
        super().traverse(callback)
        # The clip ranges are plain Python floats baked into each ray: read-only.
        callback.put("near_clip", self._near, mi.ParamFlags.ReadOnly)
        callback.put("far_clip", self._far, mi.ParamFlags.ReadOnly)
        callback.put("to_world", self.m_to_world, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        super().parameters_changed(keys)
        self._validate()

    # --------------------------------------------------------- Python helpers

    @property
    def near_clip(self) -> float:
        """Minimum range (metres): rays start this far along their beam."""
        return self._near

    @property
    def far_clip(self) -> float:
        """Maximum range (metres) measured from the sensor."""
        return self._far

    @property
    def width(self) -> int:
        """Film width: azimuth steps (or rays in the explicit-ray mode)."""
        return self._width

    @property
    def height(self) -> int:
        """Film height: beams (1 in the explicit-ray mode)."""
        return self._height

    @property
    def explicit_rays(self) -> bool:
        """True in the explicit-ray mode (``rays``)."""
        return self._rays_local is not None

    @property
    def n_beams(self) -> int:
        """Number of beams (film height; in ``rays`` mode the ray list's beams)."""
        return self._n_beams

    def beam_index(self) -> mi.UInt32:
        """Beam of every pixel, row-major (index ``row * W + col``)."""
        return mi.UInt32(self._beams)

    def beam_at(self, position_sample) -> mi.UInt32:
        """Beam of the pixel that :py:meth:`sample_ray` traces for ``position_sample``."""
        return dr.gather(mi.UInt32, self._beams, self._pixel_index(position_sample))

    def beam_grid(self):
        """Beam elevations (H,) and column azimuths (W,) in radians (numpy float64).

        Row 0 is the top beam; azimuth ``phi(col) = pi (1 - 2 (col + 0.5) / W)``.
        Not defined in the explicit-ray mode.
        """
        if self._rays_local is not None:
            raise LidarError("lidar: beam_grid() is undefined for the explicit-ray "
                             "mode ('rays'); use ray_directions_local()")
        elevations = np.deg2rad(self._elevations_deg)
        cols = np.arange(self._width, dtype=np.float64)
        azimuths = np.pi * (1.0 - 2.0 * (cols + 0.5) / self._width)
        return elevations, azimuths

    def ray_directions_local(self) -> np.ndarray:
        """Unit beam directions in the sensor frame, numpy (H, W, 3) float64."""
        if self._rays_local is not None:
            return self._rays_local[None, :, 3:].copy()
        elev, azim = self.beam_grid()
        ce = np.cos(elev)[:, None]
        return np.stack([ce * np.cos(azim)[None, :],
                         ce * np.sin(azim)[None, :],
                         np.broadcast_to(np.sin(elev)[:, None], (elev.size, azim.size))],
                        axis=-1)

    def origin(self) -> mi.Point3f:
        """Sensor position in world space."""
        return self.m_to_world @ mi.Point3f(0.0, 0.0, 0.0)

    def all_rays(self, clip: bool = True, time: float = 0.0) -> mi.Ray3f:
        """One world-space ray per pixel, row-major (index ``row * W + col``).

        With ``clip`` (default) the rays are exactly those of :py:meth:`sample_ray`:
        origins ``near_clip`` along the beam and ``maxt = far_clip - near_clip``.
        With ``clip=False`` they start at the sensor (or the given origins of the
        explicit-ray mode) and ``maxt = far_clip``.
        """
        idx = dr.arange(mi.UInt32, self._width * self._height)
        return self._rays_at(idx, mi.Float(time), mi.Bool(True), clip)

    # ------------------------------------------------------------ Mitsuba API

    def _rays_at(self, idx, time, active, clip):
        d_local = dr.gather(mi.Vector3f, self._dirs, idx, active)
        if self._origins is None:
            o_local = mi.Point3f(0.0)
        else:
            o_local = dr.gather(mi.Point3f, self._origins, idx, active)
        to_world = self.m_to_world
        d = dr.normalize(to_world @ d_local)
        o = to_world @ o_local
        near = self._near if clip else 0.0
        if near > 0.0:
            o = dr.fma(d, near, o)
        return mi.Ray3f(o, d, mi.Float(self._far - near), time, mi.Color0f())

    def _pixel_index(self, position_sample):
        # Integrators pass positions in [0, 1)^2 over the crop window (as for
        # Mitsuba's cameras); map them back to the full film's pixel.
        film = self.film()
        crop_size = mi.ScalarVector2f(film.crop_size())
        crop_offset = mi.ScalarVector2i(film.crop_offset())
        pixel = mi.Vector2i(dr.floor(position_sample * crop_size)) + crop_offset
        col = dr.clip(pixel.x, 0, self._width - 1)
        row = dr.clip(pixel.y, 0, self._height - 1)
        return mi.UInt32(row * self._width + col)

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        ray = self._rays_at(self._pixel_index(sample2), time, active, True)
        # RGB variants: no wavelengths to sample, weight 1.
        return ray, mi.Spectrum(1.0)

    def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
        ray, weight = self.sample_ray(time, sample1, sample2, sample3, active)
        # Beams are exact rays: there is no pixel footprint to differentiate.
        ray_diff = mi.RayDifferential3f(ray)
        ray_diff.has_differentials = False
        return ray_diff, weight

    def bbox(self):
        # matrix.numpy() is (4, 4, 1): one JIT lane of a 4x4 matrix.
        p = mi.ScalarPoint3f(*(float(v) for v in self.m_to_world.matrix.numpy()[:3, 3, 0]))
        return mi.ScalarBoundingBox3f(p, p)

    def to_string(self):
        mode = ("rays=%d" % self._rays_local.shape[0] if self._rays_local is not None
                else "beams=%d, elevation=[%g, %g] deg" % (
                    self._height, self._elevations_deg[0], self._elevations_deg[-1]))
        return ("LidarSensor[%s, azimuth_steps=%d, near_clip=%g, far_clip=%g]"
                % (mode, self._width, self._near, self._far))


def register():
    mi.register_sensor("lidar", lambda props: LidarSensor(props))
