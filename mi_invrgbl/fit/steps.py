"""Safe optimiser steps: NaN detection with rollback, checkpointable Adam state."""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi


class NonFiniteStep(RuntimeError):
    pass


def make_optimizer(values: dict, lrs: dict):
    """Adam over ``values`` (key -> Float), one learning rate per key.

    ``mask_updates``: a frame sees a fraction of the Gaussians; the others get
    a zero gradient and must not drift on stale momentum.
    """
    opt = mi.ad.Adam(lr=1e-3, mask_updates=True)
    for key, value in values.items():
        opt[key] = value if dr.is_array_v(value) else mi.Float(value)
        opt.set_learning_rate({key: float(lrs[key])})
    return opt


def _magnitude(value):
    """Sum of absolute values as a width-1 Float, not read back: infinite or NaN
    exactly when some entry is (or when the sum overflows, a diverging step too)."""
    total = dr.sum(dr.abs(value), axis=None)
    return total.array if isinstance(total, mi.TensorXf) else mi.Float(total)


def safe_step(opt, loss, log, lr_scale_state: dict, what="step", before_step=None):
    """Back-propagate ``loss`` and step, unless the loss or a gradient is not
    finite: then nothing changes, learning rates are halved and False returned.

    The loss and every gradient are checked with one reduction read back
    once: on a GPU each read-back waits for the device, and one per variable
    cost more than the step itself.
    """
    if not dr.width(loss):
        loss = mi.Float(0.0)
    # A term can be inert for a scene (no LiDAR scans: the LiDAR side gets no
    # gradient); that is not an error.
    dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    check = _magnitude(dr.detach(loss))
    for key in opt.keys():
        g = dr.grad(opt[key])
        if dr.width(g):
            check = check + _magnitude(g)
    if not np.isfinite(check[0]):
        value = float(loss[0])
        _lower(opt, log, lr_scale_state, "loss is %r" % value if not np.isfinite(value)
               else "a gradient is not finite", what)
        for key in opt.keys():
            dr.clear_grad(opt[key])
        return False
    if before_step is not None:
        before_step()  # e.g. read gradients, which the step clears
    opt.step()
    return True


def _lower(opt, log, state, reason, what):
    state["scale"] = state.get("scale", 1.0) * 0.5
    for key in opt.keys():
        lr = opt.learning_rate(key)
        opt.set_learning_rate({key: float(lr) * 0.5})
    state["rollbacks"] = state.get("rollbacks", 0) + 1
    log("[fit] %s skipped and rolled back (%s); learning rates halved (now x%.3g)"
        % (what, reason, state["scale"]))


def optimizer_state(opt) -> dict:
    """Adam state as numpy arrays (for checkpoints)."""
    out = {}
    for key, (value, _promoted, lr, extra) in opt.state.items():
        t, m, v, _ = extra
        out["value/" + key] = np.array(dr.detach(value), np.float32)
        out["m/" + key] = np.array(m, np.float32)
        out["v/" + key] = np.array(v, np.float32)
        out["t/" + key] = np.array(t).reshape(-1).astype(np.int64)
        out["lr/" + key] = np.float64(lr if lr is not None else opt.lr)
    return out


def _like(kind, array):
    """``array`` (from :func:`optimizer_state`) as a Dr.Jit array of type ``kind``:
    flat for ``Float``, (3, N) for the sun direction's ``Vector3f`` and the like."""
    array = np.ascontiguousarray(array, np.float32)
    return kind(array) if array.ndim == 1 else kind(*array)


def restore_optimizer(opt, state: dict):
    """Put checkpointed values and moments back into ``opt`` (same keys)."""
    for key in list(opt.keys()):
        if "value/" + key not in state:
            continue
        kind = type(opt[key])
        opt[key] = _like(kind, state["value/" + key])
        value, promoted, lr, extra = opt.state[key]
        m, v = state["m/" + key], state["v/" + key]
        if m.shape[-1] == dr.width(value):
            t = type(extra[0])(int(state["t/" + key][0])) if extra[0] is not None else extra[0]
            opt.state[key] = (value, promoted, lr,
                              (t, _like(type(extra[1]), m), _like(type(extra[2]), v), extra[3]))
        opt.set_learning_rate({key: float(state["lr/" + key])})
