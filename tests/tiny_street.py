"""The tiny synthetic street that test_import and test_bad_inputs read.

Six frames of 64 x 24 pixels and 256 azimuth steps with a moving car:
generated once per test session (the ``tiny_street`` fixture in conftest.py)
and never written to; tests that alter its files work on copies.
"""

CONFIG = dict(seed=3, frames=6, width=64, height=24, azimuth_steps=256, spp=2, night=False)


def generate(out):
    """Write the street into ``out`` (a new folder); returns ``out``."""
    from mi_invrgbl.synthetic import StreetConfig, generate_street
    generate_street(str(out), StreetConfig(**CONFIG), log=lambda *a, **k: None)
    return out
