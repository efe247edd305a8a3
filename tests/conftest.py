"""Shared pytest set-up: every test runs in the LLVM RGB autodiff variant."""

import os
import pathlib

import pytest
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_invrgbl  # noqa: E402,F401  (registers the plugins)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


@pytest.fixture
def variant():
    mi.set_variant("llvm_ad_rgb")
    return "llvm_ad_rgb"


@pytest.fixture(scope="session")
def scenes_dir():
    return ROOT / "scenes"


@pytest.fixture(scope="session")
def kitti_dir():
    path = SHARED / "data" / "kitti-raw-excerpt"
    if not path.exists():
        pytest.skip("shared KITTI excerpt not present")
    return path
