"""Mitsuba plugins of mi-invrgbl (shipped inside the wheel as ``mi_invrgbl.plugins``).

One module per plugin; each module defines ``register()`` and records the variant
its classes were built for in ``_variant``. Shared maths lives in
:mod:`mi_invrgbl.physics.brdf` (Cook-Torrance) and
:mod:`mi_invrgbl.physics.hits` (ray traversal of Gaussians).
"""
