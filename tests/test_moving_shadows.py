"""Moving objects' sun shadows on top of a learned, static sun visibility.

Stage 2 learns one ``sun_visibility`` per Gaussian, but a moving object's
shadow moves. With the field holding the static scene's shadows, each frame
multiplies it by the sun's transmittance through the moving nodes where the
frame has them (``physics.lighting.moving_shadows``). Checked here against
references that do not go through it:

* the split of one shadow trace (static x moving) against the plain
  transmittance of the same rays;
* the culled trace against every Gaussian traced without culling;
* stage 2's lighting of two frames against the field times the factor, with
  the block of tests/fit_scene.py moving 2.5 m between frames.
"""

import os

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from fit_scene import build_with_block
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.stage2 import FrozenScene, Stage2
from mi_invrgbl.physics import hits as hitlib
from mi_invrgbl.physics.lighting import (GaussianTable, point_lights, shadow_origins,
                                         split_transmittance, transmittance)

W, H, COLUMNS, FRAMES = 32, 12, 64, 3


@pytest.fixture(scope="module")
def block_scene(tmp_path_factory):
    return build_with_block(str(tmp_path_factory.mktemp("moving_shadows")), n_frames=FRAMES,
                            width=W, height=H, columns=COLUMNS)


def _state(path, tmp_path, **kw):
    cfg = FitConfig(output=str(tmp_path), fit_width=W, lidar_columns=COLUMNS, samples=8,
                    sun="on", validation_every=0, object_poses=False, **kw)
    return load_state(path, cfg, log=lambda *a: None)


def _sun(state):
    (kind, emitter), = [(k, e) for k, e in point_lights(state.scene) if k == "sun"]
    return np.array(dr.detach(emitter.sun_direction_world()), np.float64).ravel()


def _scene_table(state):
    by_id = {n.shape.id(): n for n in hitlib.gaussian_nodes(state.scene)}
    nodes = [by_id[name] for name in state.model.nodes]
    return nodes, GaussianTable.build(nodes).load_geometry()


def _block_transmittance(table, nodes, moving, d):
    """Reference in NumPy, no traversal: per shadow ray of ``table``'s
    Gaussians, the product of (1 - alpha) over the moving nodes' Gaussians
    (axis-aligned here) that the ray passes within their 3-sigma support
    (the ``gaussians`` shape's extent) ahead of its start, alpha the
    response's peak along the ray, ``min(opacity exp(-r^2 / 2), 0.99)``
    (the product does not depend on the order the ray meets them). Also
    whether the ray starts inside such a support: the traversal meets a
    Gaussian where the ray enters it, as every shadow ray of the renderer."""
    o = np.array(shadow_origins(table, dr.zeros(mi.Vector3f, table.total)
                                + mi.Vector3f(*[float(x) for x in d])), np.float64).T
    block = np.concatenate([np.array(n.data, np.float64).reshape(-1, 10) for n in nodes
                            if n.id in moving])
    opac = np.concatenate([np.array(n.opacities, np.float64) for n in nodes if n.id in moving])
    assert np.allclose(np.abs(block[:, 9]), 1.0), "the reference assumes unrotated Gaussians"
    u = np.asarray(d, np.float64) / np.linalg.norm(d)
    rel = (block[None, :, :3] - o[:, None, :]) / block[None, :, 3:6]
    du = u[None, :] / block[:, 3:6]
    t = np.sum(rel * du[None], axis=2) / np.sum(du * du, axis=1)[None]
    r = np.linalg.norm(rel - t[..., None] * du[None], axis=2)
    alpha = np.where((t > 0) & (r < 3.0), np.minimum(opac[None] * np.exp(-0.5 * r * r), 0.99), 0.0)
    inside = np.linalg.norm(rel, axis=2).min(axis=1) < 3.0
    return np.prod(1.0 - alpha, axis=1), inside


def test_the_moving_factor_is_the_product_over_the_moving_gaussians_and_the_split_the_plain_trace(
        block_scene, tmp_path):
    state = _state(block_scene, tmp_path)
    frozen = FrozenScene(state, state.train_frames)
    d = _sun(state)
    moving = frozen.moving_ids
    assert len(moving) == 1
    for frame in (state.train_frames[0], state.train_frames[-1]):
        factor = np.array(frozen.moving_shadow(frame, d))
        state.model.push(frame.poses, stage=2)
        nodes, table = _scene_table(state)
        own = np.isin(np.array(table.ids), list(moving))
        reference, inside = _block_transmittance(table, nodes, moving, d)
        # Culled or not, traced through the objects alone: the product over
        # their Gaussians. A shadow ray stops after 16 Gaussians
        # (lighting.SHADOW_MAX_HITS), so below 5 % the two need only agree
        # that it is dark.
        check = ~own & ~inside
        assert check.sum() > 0.95 * (~own).sum()
        np.testing.assert_allclose(np.maximum(factor[check], 0.05),
                                   np.maximum(reference[check], 0.05), atol=2e-3)
        assert np.all(factor[own] == 1.0)
        # The block shadows some of the scene in this frame (else the test
        # could not fail).
        assert np.sum(factor < 0.5) >= 5
        # One trace split in two multiplies back to the plain transmittance.
        dv = dr.zeros(mi.Vector3f, table.total) + mi.Vector3f(*[float(x) for x in d])
        o = shadow_origins(table, dv)
        with dr.suspend_grad():
            plain = np.array(transmittance(state.scene, o, dv, mi.Float(dr.inf), nodes))
            static, through = split_transmittance(state.scene, o, dv, mi.Float(dr.inf), nodes, moving)
        np.testing.assert_allclose(np.array(static) * np.array(through), plain, atol=2e-5)
    first = np.array(frozen.moving_shadow(state.train_frames[0], d))
    last = np.array(frozen.moving_shadow(state.train_frames[-1], d))
    # The shadow moved with the block.
    assert np.sum(np.abs(first - last) > 0.5) >= 10
    # Tracing it left the scene's shapes as they were named (the scene of
    # the moving shapes alone is keyed by their ids).
    assert [s.id() for s in state.scene.shapes() if s.is_ellipsoids()] == list(state.model.nodes)


def test_stage2_lights_each_frame_with_the_field_times_its_moving_shadow(block_scene, tmp_path):
    state = _state(block_scene, tmp_path)
    frames = state.train_frames
    stage2 = Stage2(state, FrozenScene(state, frames))
    assert stage2.learn_sun_visibility and stage2.moving_shadows
    vals = stage2.values()
    d = _sun(state)
    lit = {}
    with dr.suspend_grad():
        for frame in (frames[0], frames[-1]):
            nodes = stage2.frozen.nodes(frame, vals)
            lighting = stage2.lighting(nodes, stage2.frozen.cache(frame), frame=frame)
            field = np.array(hitlib.gather_attribute(nodes, "sun_visibility", lighting.table.ids,
                                                     lighting.table.prims, mi.Bool(True)))
            irr = np.array(lighting.light_irr[0])[0]
            factor = np.array(stage2.frozen.moving_shadow(frame, d))
            e = float(np.array(dr.detach(state.params[state.sun_key])).ravel()[0])
            np.testing.assert_allclose(irr, e * field * factor, rtol=1e-5, atol=1e-6)
            lit[frame.index] = irr
    assert np.sum(np.abs(lit[frames[0].index] - lit[frames[-1].index]) > 0.1 * e) >= 10

    # Switched off, every frame is lit by the field alone.
    state_off = _state(block_scene, tmp_path / "off", moving_shadows=False)
    stage2_off = Stage2(state_off, FrozenScene(state_off, state_off.train_frames))
    assert not stage2_off.moving_shadows
    with dr.suspend_grad():
        irr_off = []
        for frame in (state_off.train_frames[0], state_off.train_frames[-1]):
            nodes = stage2_off.frozen.nodes(frame, stage2_off.values())
            lighting = stage2_off.lighting(nodes, stage2_off.frozen.cache(frame), frame=frame)
            irr_off.append(np.array(lighting.light_irr[0])[0])
    np.testing.assert_array_equal(irr_off[0], irr_off[1])


def test_per_frame_visibility_traces_the_moving_shadows_itself(block_scene, tmp_path):
    # With every frame's visibility traced through the placed objects, the
    # factor would count the objects twice: it is not used.
    state = _state(block_scene, tmp_path, per_frame_visibility=True)
    stage2 = Stage2(state, FrozenScene(state, state.train_frames))
    assert stage2.learn_sun_visibility and not stage2.moving_shadows


def test_the_fitted_scene_names_its_moving_shapes_for_the_integrator(block_scene, tmp_path):
    from mi_invrgbl.fit.outputs import fitted_xml
    from mi_invrgbl.fit.runner import start_stage2
    for on in (True, False):
        state = _state(block_scene, tmp_path / str(on), moving_shadows=on)
        start_stage2(state, FrozenScene(state, state.train_frames), initialise=False)
        assert state.sun_visibility_learned and state.moving_shadows == on
        # Next to the scene: its PLYs are named relative to it.
        path = os.path.join(os.path.dirname(block_scene), "fitted_%s.xml" % on)
        with open(path, "w") as f:
            f.write(fitted_xml(state))
        settings = mi.load_file(path).integrator().settings()
        assert settings["sun_visibility"] == "attribute"
        assert settings["moving"] == ("object_1" if on else "")


@pytest.mark.parametrize("d", [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)],
                         ids=["overhead", "along x", "along -y"])
def test_a_sun_along_an_axis_casts_the_product_over_the_moving_gaussians(block_scene, tmp_path, d):
    # A direction along an axis makes the slab test divide by zero on the
    # other two axes: rays level with a face must neither all pass nor all
    # miss the box.
    from mi_invrgbl.physics.lighting import moving_shadows
    state = _state(block_scene, tmp_path)
    frame = state.train_frames[0]
    state.model.push(frame.poses, stage=2)
    nodes, table = _scene_table(state)
    moving = FrozenScene(state, state.train_frames).moving_ids
    factor, rays = moving_shadows(nodes, table, d, moving, return_rays=True)
    factor = np.array(factor)
    assert np.all(np.isfinite(factor))
    own = np.isin(np.array(table.ids), list(moving))
    reference, inside = _block_transmittance(table, nodes, moving, d)
    check = ~own & ~inside
    np.testing.assert_allclose(np.maximum(factor[check], 0.05),
                               np.maximum(reference[check], 0.05), atol=2e-3)
    # Only the rays that can meet the block were traced (a darkened ray left
    # out would read 1 above).
    assert 0 < rays < table.total
    if d[2] > 0:
        assert np.sum(factor < 0.5) >= 5     # the ground under the block


def test_no_moving_node_or_an_unknown_id_traces_nothing(block_scene, tmp_path):
    from mi_invrgbl.physics.lighting import moving_shadows
    state = _state(block_scene, tmp_path)
    nodes, table = _scene_table(state)
    for ids in ([], [int(np.max(np.array(table.ids))) + 1000]):
        factor, rays = moving_shadows(nodes, table, _sun(state), ids, return_rays=True)
        assert rays == 0
        np.testing.assert_array_equal(np.array(factor), np.ones(table.total, np.float32))
