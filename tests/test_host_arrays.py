"""NumPy arrays that end just before an unmapped page, handed to Dr.Jit."""

import ctypes
import mmap
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from mi_invrgbl.physics.host_arrays import PAD_BYTES, jit_array

N = 1000    # not a multiple of 16: the last SIMD packet runs past the data


def _guarded(dtype, count):
    """``count`` values of ``dtype`` ending exactly at a page that may not be
    read (mprotect PROT_NONE); the mapping stays alive with the array."""
    page = mmap.PAGESIZE
    buf = mmap.mmap(-1, 2 * page, prot=mmap.PROT_READ | mmap.PROT_WRITE)
    addr = ctypes.addressof(ctypes.c_char.from_buffer(buf))
    if ctypes.CDLL(None).mprotect(ctypes.c_void_p(addr + page), page, 0) != 0:
        pytest.skip("mprotect not available")
    itemsize = np.dtype(dtype).itemsize
    return np.frombuffer(buf, dtype=dtype, count=count, offset=page - itemsize * count)


def test_an_array_at_a_guard_page_is_read_safely():
    if not mi.variant().startswith("llvm"):
        pytest.skip("the overrun is the LLVM backend's")
    a = _guarded(np.float32, N)
    a[:] = np.arange(N, dtype=np.float32)
    f = jit_array(mi.Float, a)
    g = f * 2.0 + 1.0
    dr.eval(g)
    np.testing.assert_array_equal(np.array(g), 2 * np.arange(N) + 1)
    idx = _guarded(np.uint32, N)
    idx[:] = np.arange(N) % 7
    out = dr.zeros(mi.Float, 7)
    dr.scatter_reduce(dr.ReduceOp.Add, out, dr.full(mi.Float, 1.0, N), jit_array(mi.UInt32, idx))
    assert np.array(out).sum() == N
    # A copy: writing the source later does not change the Dr.Jit array.
    a[0] = -5.0
    assert f[0] == 0.0


def test_the_plain_constructor_reads_past_a_numpy_buffer():
    # Why jit_array exists: the same array handed to mi.Float as it is
    # (no copy on LLVM) crashes the kernel that reads it. Run apart, so that
    # the crash does not take the test session with it.
    if not mi.variant().startswith("llvm"):
        pytest.skip("the overrun is the LLVM backend's")
    code = textwrap.dedent("""
        import ctypes, mmap, numpy as np, drjit as dr, mitsuba as mi
        mi.set_variant("llvm_ad_rgb")
        page = mmap.PAGESIZE
        buf = mmap.mmap(-1, 2 * page, prot=mmap.PROT_READ | mmap.PROT_WRITE)
        addr = ctypes.addressof(ctypes.c_char.from_buffer(buf))
        assert ctypes.CDLL(None).mprotect(ctypes.c_void_p(addr + page), page, 0) == 0
        a = np.frombuffer(buf, dtype=np.float32, count=%d, offset=page - 4 * %d)
        a[:] = 1.0
        g = mi.Float(a) * 2.0
        dr.eval(g)
        print(float(g[0]))
    """ % (N, N))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    if run.returncode == 0:
        pytest.skip("this Dr.Jit copies NumPy data or pads its reads: nothing to guard against")
    assert run.returncode < 0 or run.returncode == 139, run.stderr[-500:]


def test_empty_and_typed_inputs():
    assert dr.width(jit_array(mi.Float, np.zeros(0))) == 0
    assert np.array(jit_array(mi.UInt32, [3, 1, 2])).tolist() == [3, 1, 2]
    assert np.array(jit_array(mi.Bool, np.array([True, False]))).tolist() == [True, False]
    # float64 and 2-D inputs: converted and flattened.
    np.testing.assert_array_equal(np.array(jit_array(mi.Float, np.ones((2, 3)))), np.ones(6))
    assert PAD_BYTES >= 64


def test_no_numpy_array_reaches_dr_jit_unpadded():
    # A guard on the code: the usual ways of handing a fresh NumPy array to a
    # Dr.Jit constructor (np.* calls, .astype, .ravel(), .copy()) go through
    # jit_array instead.
    import re
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "mi_invrgbl"
    pattern = re.compile(r"mi\.(Float|UInt32|Int32|Bool|TensorXf)\((np\.|[^()]*\.astype\(|"
                         r"[^()]*\.ravel\(\)|[^()]*\.copy\(\))")
    found = ["%s:%d" % (p.relative_to(root.parent), i + 1)
             for p in sorted(root.rglob("*.py")) if p.name != "host_arrays.py"
             for i, line in enumerate(p.read_text().splitlines()) if pattern.search(line)]
    assert found == [], found
