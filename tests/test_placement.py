"""Stage 2 traces the Gaussians' sky visibility through the scene with the
moving objects where the traced geometry has them.

A trace starts from the frozen geometry of one frame (the shared cache's
reference frame, or each frame with ``per_frame_visibility``) and goes through
the scene as it was last pushed. Here the fit scene of tests/fit_scene.py gets
a block of Gaussians that drives along the street between the frames, and
every cache stage 2 fills is compared with a trace made from scratch with the
scene placed for that cache's frame.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from fit_scene import build_with_block
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.stage2 import FrozenScene, Stage2
from mi_invrgbl.physics.lighting import GaussianLighting, LightingCache

W, H, COLUMNS, FRAMES = 32, 12, 64, 4


@pytest.fixture(scope="module")
def moving_scene(tmp_path_factory):
    """The fit scene with ``object_1``, a 1 m block of 125 Gaussians 0.6 m
    above the road, 2.5 m further down the street at every frame."""
    return build_with_block(str(tmp_path_factory.mktemp("placement")), n_frames=FRAMES,
                            width=W, height=H, columns=COLUMNS)


def _state(path, tmp_path, per_frame):
    cfg = FitConfig(output=str(tmp_path), fit_width=W, lidar_columns=COLUMNS, samples=8,
                    sun="on", validation_every=0, object_poses=False,
                    per_frame_visibility=per_frame)
    return load_state(path, cfg, log=lambda *a: None)


def _fresh_visibility(state, stage2, frame):
    """Sky visibility traced now, with the scene pushed at ``frame``'s poses."""
    state.model.push(frame.poses, stage=2)
    cache = LightingCache()
    with dr.suspend_grad():
        GaussianLighting(state.scene, stage2.frozen.nodes(frame, stage2.values()),
                         state.config.samples, cache, trace_sun=not stage2.learn_sun_visibility,
                         bounces=state.config.bounces)
    return np.array(cache.sky_visibility)


def test_per_frame_caches_are_traced_with_the_objects_at_their_frame(moving_scene, tmp_path):
    state = _state(moving_scene, tmp_path, per_frame=True)
    frames = state.train_frames
    assert len(frames) == FRAMES
    stage2 = Stage2(state, FrozenScene(state, frames))
    state.model.push(frames[0].poses, stage=2)   # where stage 2's start leaves the scene
    stage2.trace_patterns()
    cached = {f.index: np.array(stage2.frozen.caches[f.index].sky_visibility) for f in frames}
    for f in frames:
        np.testing.assert_allclose(cached[f.index], _fresh_visibility(state, stage2, f), atol=1e-6)
    # The block's move changes what the Gaussians see of the sky (else this test could not fail).
    assert np.mean(np.abs(cached[frames[0].index] - cached[frames[-1].index]) > 0.1) > 1e-3


def test_the_shared_cache_is_traced_at_its_reference_frame(moving_scene, tmp_path):
    state = _state(moving_scene, tmp_path, per_frame=False)
    frames = state.train_frames
    frozen = FrozenScene(state, frames[::-1])     # the reference is the first *training* frame
    assert frozen.first is frames[0]
    stage2 = Stage2(state, frozen)
    state.model.push(frames[-1].poses, stage=2)   # something else moved the objects last
    stage2.trace_patterns()
    cached = np.array(frozen.caches[frames[0].index].sky_visibility)
    np.testing.assert_allclose(cached, _fresh_visibility(state, stage2, frames[0]), atol=1e-6)
    assert not np.allclose(cached, _fresh_visibility(state, stage2, frames[-1]), atol=1e-3)


def test_an_out_of_date_cache_is_traced_again_at_its_reference_frame(moving_scene, tmp_path):
    # A filled cache whose key no longer matches (a traced sun that moved, a
    # new geometry) is traced again inside the lighting; the objects must be
    # placed for it then too, not only for an empty cache.
    state = _state(moving_scene, tmp_path, per_frame=False)
    frames = state.train_frames
    frozen = FrozenScene(state, frames)
    stage2 = Stage2(state, frozen)
    stage2.trace_patterns()
    cache = frozen.caches[frames[0].index]
    reference = np.array(cache.sky_visibility)
    state.model.push(frames[-1].poses, stage=2)   # the objects elsewhere...
    cache.key = ("out of date",)                  # ...when the cache must be traced again
    with dr.suspend_grad():
        stage2.lighting(frozen.nodes(frames[1], stage2.values()), cache, frame=frames[1])
    assert cache.key != ("out of date",)
    np.testing.assert_allclose(np.array(cache.sky_visibility), reference, atol=1e-6)


def test_stage1_scores_see_the_pose_corrections_its_steps_made(moving_scene, tmp_path):
    """A stage-1 step renders with the objects' pose corrections themselves
    and bakes no frame's poses (that cost 6 % of a KITTI step); a
    score, a snapshot or the stage's end bakes them first, so what it reads
    in ``frame.poses`` is where the steps have moved the objects."""
    from mi_invrgbl.fit.evaluate import score_stage1
    from mi_invrgbl.fit.object_poses import correction_matrix
    from mi_invrgbl.fit.stage1 import Stage1
    cfg = FitConfig(output=str(tmp_path), fit_width=W, lidar_columns=COLUMNS, samples=8,
                    batch_rays=256, lidar_batch_rays=128, seed=2)
    state = load_state(moving_scene, cfg, log=lambda *a: None)
    assert state.object_poses
    s1 = Stage1(state)
    bakes = []
    bake = state.object_poses.bake
    state.object_poses.bake = lambda: (bakes.append(1), bake())[1]
    before = [dict(f.poses) for f in state.observations]
    for it in range(1, 13):
        s1.iteration(it)
    assert not bakes
    # Frames read the poses as they were until a score bakes the steps' corrections.
    np.testing.assert_allclose(state.observations[0].poses["object_1"], before[0]["object_1"])
    score = s1.score(state.validation_frames or state.train_frames)
    assert len(bakes) == 1 and np.isfinite(score)
    table = state.object_poses.table("object_1")      # (the last step's values, pulled)
    assert np.abs(table).max() > 1e-4
    for k, f in enumerate(state.observations):
        want = state.object_poses.base[k]["object_1"] @ correction_matrix(table[k])
        np.testing.assert_allclose(f.poses["object_1"], want, atol=1e-9)
    # The same score as a pull followed by the plain scorer.
    s1.pull()
    assert score == pytest.approx(score_stage1(state, state.validation_frames or state.train_frames))
