"""mi-invrgbl: InvRGB+L inverse rendering of camera + LiDAR scenes in Mitsuba 3.

Import this package *after* choosing a Mitsuba variant::

    import mitsuba as mi
    mi.set_variant('llvm_ad_rgb')      # or 'cuda_ad_rgb'
    import mi_invrgbl                  # registers every plugin by name

From then on ``mi.load_file`` understands the plugin names ``gaussians``,
``cooktorrance``, ``shsun``, ``lidar``, ``laser``, ``lidar_return`` and
``invrgbl``. A later ``mi.set_variant`` re-registers them for the new variant.
"""

from .variant import check_variant, register_plugins, UnsupportedVariantError

__version__ = "0.1.0"

check_variant()
register_plugins()

__all__ = ["check_variant", "register_plugins", "UnsupportedVariantError", "__version__"]
