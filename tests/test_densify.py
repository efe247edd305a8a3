"""Stage 1's densification quota: ranked within each node or over the scene.

The fit scene of tests/fit_scene.py with a moving block (a second node) gets
positional-gradient accumulations set by hand: the block's Gaussians a
thousand times larger than any of the background's. Ranked per node
(``densify_scope="node"``) each node splits its own top share; ranked over
the scene the splits go to the largest gradients wherever they are.
"""

import numpy as np
import pytest
import mitsuba as mi

from fit_scene import build_with_block
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.stage1 import Stage1

FRACTION = 0.1


@pytest.fixture(scope="module")
def scene_with_block(tmp_path_factory):
    return build_with_block(str(tmp_path_factory.mktemp("densify")))


def _densified(path, tmp_path, scope):
    """Splits per node after one densification with hand-set gradients, the
    node counts before it, and the gradients set."""
    cfg = FitConfig(output=str(tmp_path), fit_width=32, lidar_columns=64, validation_every=0,
                    object_poses=False, densify_scope=scope, densify_fraction=FRACTION,
                    prune_opacity=0.0)
    state = load_state(path, cfg, log=lambda *a: None)
    s1 = Stage1(state)
    rng = np.random.default_rng(4)
    counts = {name: node.count for name, node in state.model.nodes.items()}
    grads = {}
    for name, n in counts.items():
        scale = 1.0 if name == "object_1" else 1e-3
        grads[name] = (scale * (1.0 + rng.random(n))).astype(np.float32)
        # Summed over three steps each: the mean is what is ranked.
        s1.grad_accum[name] = [mi.Float(3.0 * grads[name]), mi.Float(np.full(n, 3.0, np.float32))]
    report = s1.densify()
    return {name: r[2] for name, r in report.items()}, counts, grads


def test_node_scope_splits_the_top_share_of_every_node(scene_with_block, tmp_path):
    split, counts, _ = _densified(scene_with_block, tmp_path, "node")
    assert set(split) == {"background", "object_1"} and counts["object_1"] == 125
    for name, n in counts.items():
        assert abs(split[name] - FRACTION * n) <= 1, (name, split[name], n)


def test_scene_scope_splits_the_largest_gradients_of_the_scene(scene_with_block, tmp_path):
    split, counts, grads = _densified(scene_with_block, tmp_path, "scene")
    total = sum(counts.values())
    assert FRACTION * total > counts["object_1"] + 10     # the quota reaches the background
    # Every block Gaussian outranks every background one: all of them split,
    # and the background fills the rest of the scene's quota.
    assert split["object_1"] == counts["object_1"]
    assert abs(split["background"] - (FRACTION * total - counts["object_1"])) <= 1
    # The background's split ones are its largest gradients.
    cut = np.percentile(np.concatenate(list(grads.values())), 100 * (1 - FRACTION))
    assert split["background"] == int((grads["background"] >= cut).sum())


def test_scene_scope_with_no_gradients_splits_nothing(scene_with_block, tmp_path):
    cfg = FitConfig(output=str(tmp_path), fit_width=32, lidar_columns=64, validation_every=0,
                    object_poses=False, densify_scope="scene", prune_opacity=0.0)
    s1 = Stage1(load_state(scene_with_block, cfg, log=lambda *a: None))
    counts = {name: node.count for name, node in s1.model.nodes.items()}
    report = s1.densify()     # no step taken: nothing accumulated
    assert all(r[2] == 0 for r in report.values())
    assert {name: r[3] for name, r in report.items()} == counts
