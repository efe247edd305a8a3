"""Real spherical harmonics up to order 3, in numpy, matching ``dr.sh_eval``.

Convention (the one of Dr.Jit's ``dr.sh_eval`` and of Sloan's "Efficient Spherical
Harmonic Evaluation"): orthonormal real SH on the unit sphere, indexed
``k = l*(l+1) + m`` for ``l = 0..order``, ``m = -l..l``, with the polar axis along
+z and the Condon-Shortley phase included, e.g.

    Y_0      =  0.282095
    Y_1..3   = -0.488603 y,  0.488603 z,  -0.488603 x

so ``∫ Y_i Y_j dω = δ_ij`` and a radiance ``L(d) = Σ_k c_k Y_k(d)`` has
``c_k = ∫ L(d) Y_k(d) dω``. Coefficient arrays are ``(K, 3)`` (one RGB triple per
basis function, ``K = (order+1)**2``); flattened they are coefficient-major
``c0.r c0.g c0.b c1.r ...``.

This module needs only numpy, so code without a Mitsuba variant can use it.
"""

from __future__ import annotations

import numpy as np

#: Highest SH order supported (the paper's sky uses order 3: 16 coefficients).
MAX_ORDER = 3

#: Y_0, the constant basis function: a constant radiance L has c_0 = L / Y0.
Y0 = 0.28209479177387814


def num_coeffs(order: int) -> int:
    """Number of basis functions up to ``order``: ``(order+1)**2``."""
    return (order + 1) ** 2


def order_from_count(count: int) -> int:
    """SH order whose basis has ``count`` functions; ValueError if none does."""
    for order in range(MAX_ORDER + 1):
        if num_coeffs(order) == count:
            return order
    raise ValueError("%d SH basis functions do not make a complete order 0..%d "
                     "(expected 1, 4, 9 or 16)" % (count, MAX_ORDER))


def sh_basis_numpy(dirs, order: int) -> np.ndarray:
    """Real SH basis at unit directions ``dirs`` (N,3): array (N, (order+1)**2)."""
    if not 0 <= order <= MAX_ORDER:
        raise ValueError("SH order must be in 0..%d, got %r" % (MAX_ORDER, order))
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    one = np.ones_like(x)
    bands = [[Y0 * one]]
    if order >= 1:
        c1 = 0.4886025119029199
        bands.append([-c1 * y, c1 * z, -c1 * x])
    if order >= 2:
        c2a, c2b, c2c = 1.0925484305920792, 0.31539156525252005, 0.5462742152960396
        bands.append([c2a * x * y, -c2a * y * z, c2b * (3 * z * z - 1),
                      -c2a * x * z, c2c * (x * x - y * y)])
    if order >= 3:
        c3a, c3b, c3c = 0.5900435899266435, 2.890611442640554, 0.4570457994644658
        c3d, c3e = 0.3731763325901154, 1.445305721320277
        bands.append([-c3a * y * (3 * x * x - y * y), c3b * x * y * z,
                      -c3c * y * (5 * z * z - 1), c3d * z * (5 * z * z - 3),
                      -c3c * x * (5 * z * z - 1), c3e * z * (x * x - y * y),
                      -c3a * x * (x * x - 3 * y * y)])
    return np.stack([f for band in bands for f in band], axis=1)


def as_coeffs(coeffs) -> np.ndarray:
    """Coefficients as a float64 (K,3) array (accepts a flat coefficient-major list)."""
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim == 1:
        if c.size % 3:
            raise ValueError("flat SH coefficient list must hold 3 values (RGB) per "
                             "basis function, got %d values" % c.size)
        c = c.reshape(-1, 3)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError("SH coefficients must be (K,3), got shape %s" % (c.shape,))
    order_from_count(c.shape[0])
    return c


def eval_sh_numpy(coeffs, dirs) -> np.ndarray:
    """Evaluate ``Σ_k c_k Y_k(d)`` (no clamping) at unit ``dirs`` (N,3): (N,3) rgb."""
    c = as_coeffs(coeffs)
    return sh_basis_numpy(dirs, order_from_count(c.shape[0])) @ c


def sphere_quadrature(n: int = 64):
    """Directions (M,3) and weights (M,) integrating exactly over the sphere any
    polynomial in (x, y, z) of degree < ``n`` (Gauss-Legendre in z, uniform in φ)."""
    z, wz = np.polynomial.legendre.leggauss(n)
    n_phi = 2 * n
    phi = (np.arange(n_phi) + 0.5) * (2 * np.pi / n_phi)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(np.maximum(0.0, 1.0 - zz * zz))
    dirs = np.stack([s * np.cos(pp), s * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    weights = np.repeat(wz * (2 * np.pi / n_phi), n_phi)
    return dirs, weights


def project_sh(fn, order: int, n: int = 64) -> np.ndarray:
    """Project a radiance function onto real SH up to ``order``: (K,3) coefficients.

    ``fn`` maps unit directions (N,3) to rgb (N,3) (a (N,) result is taken as grey).
    The quadrature (``n`` Gauss-Legendre nodes in z times 2n in φ) is exact for
    skies that are polynomials of degree < n in the direction, which includes every
    SH sky of order < n/2; smooth skies converge quickly with ``n``.
    """
    dirs, w = sphere_quadrature(n)
    values = np.asarray(fn(dirs), dtype=np.float64)
    if values.ndim == 1:
        values = np.repeat(values[:, None], 3, axis=1)
    if values.shape != (dirs.shape[0], 3):
        raise ValueError("fn must map (N,3) directions to (N,3) rgb, got shape %s"
                         % (values.shape,))
    basis = sh_basis_numpy(dirs, order)
    return basis.T @ (values * w[:, None])
