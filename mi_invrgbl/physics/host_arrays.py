"""NumPy data handed to Dr.Jit, safely.

On the LLVM backend ``mi.Float(ndarray)`` (likewise ``UInt32``, ``Int32``,
``Bool``) of a C-contiguous array of the matching dtype does not copy: the
Dr.Jit array uses the NumPy buffer itself. Dr.Jit's CPU kernels then read it
in whole SIMD packets, up to a packet past the last element, which its own
allocations leave room for and a NumPy buffer does not: where the buffer
ends just before an unmapped page, the kernel dies of SIGSEGV. Large NumPy
arrays are mapped pages of their own (glibc's ``mmap`` threshold), so the
chance is small per array but real per fit: budgeted fits died of SIGSEGV
in stage 2, rendering right after their lighting caches were re-written
from NumPy (``tests/test_host_arrays.py`` builds an array that ends at a
guard page to show the overrun).

:func:`jit_array` copies the data into a NumPy buffer with :data:`PAD_BYTES`
of slack after it and hands Dr.Jit a view of that, so the packet past the
end stays inside memory the array owns. Use it for every NumPy array that
becomes a Dr.Jit array and may be large.
"""

from __future__ import annotations

import numpy as np
import drjit as dr

#: Slack after the data: one 16-wide SIMD packet of 8-byte values.
PAD_BYTES = 128

_DTYPES = {dr.VarType.Float32: np.float32, dr.VarType.UInt32: np.uint32,
           dr.VarType.Int32: np.int32, dr.VarType.Bool: np.bool_}


def jit_array(kind, values):
    """A flat Dr.Jit array of type ``kind`` (``mi.Float``, ``mi.UInt32``,
    ``mi.Int32`` or ``mi.Bool``) holding ``values`` (anything NumPy reads),
    in a buffer Dr.Jit's kernels may read whole packets of."""
    dtype = np.dtype(_DTYPES[dr.type_v(kind)])
    flat = np.asarray(values).ravel()
    buf = np.zeros(flat.size + PAD_BYTES // dtype.itemsize, dtype)
    buf[:flat.size] = flat
    return kind(buf[:flat.size])


def jit_tensor(values):
    """``mi.TensorXf`` of ``values`` (float32, its NumPy shape) in a padded
    buffer, as :func:`jit_array`."""
    import mitsuba as mi
    a = np.asarray(values, np.float32)
    return mi.TensorXf(jit_array(mi.Float, a), a.shape)
