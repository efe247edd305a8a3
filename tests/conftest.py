"""Shared pytest set-up: every test runs in one Mitsuba variant.

``pytest --variant cuda_ad_rgb`` (or ``MI_INVRGBL_VARIANT=cuda_ad_rgb``) runs the
suite on a GPU; the default is ``llvm_ad_rgb``.
"""

import os
import pathlib

import pytest
import mitsuba as mi

import tiny_street as tiny_street_data
import variant_choice


def pytest_addoption(parser):
    parser.addoption("--variant", default=None,
                     help="Mitsuba variant to test (default: $MI_INVRGBL_VARIANT or llvm_ad_rgb)")


def pytest_configure(config):
    chosen = config.getoption("--variant")
    if chosen:
        os.environ["MI_INVRGBL_VARIANT"] = chosen
    try:
        variant_choice.use()
    except SystemExit as exc:  # e.g. cuda_ad_rgb on a machine without a GPU
        pytest.exit(str(exc), returncode=4)
    import mi_invrgbl  # noqa: F401  (registers the plugins for the chosen variant)



def pytest_report_header(config):
    return "mitsuba variant: %s" % variant_choice.variant()

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


@pytest.fixture
def variant():
    return variant_choice.use()


@pytest.fixture(scope="session")
def scenes_dir():
    return ROOT / "scenes"


@pytest.fixture(scope="session")
def kitti_dir():
    path = SHARED / "data" / "kitti-raw-excerpt"
    if not path.exists():
        pytest.skip("shared KITTI excerpt not present")
    return path


@pytest.fixture(scope="session")
def tiny_street(tmp_path_factory):
    """The tiny synthetic street of :mod:`tiny_street` (read only)."""
    variant_choice.use()
    return tiny_street_data.generate(tmp_path_factory.mktemp("tiny_street") / "street")
