"""``mi-invrgbl fit``'s flags are generated from FitConfig: one source of defaults."""

import dataclasses

import pytest

from mi_invrgbl.cli import build_parser
from mi_invrgbl.commands.fit import FLAGS, config_from_args
from mi_invrgbl.errors import UserError
from mi_invrgbl.fit.config import FitConfig


def parse(*args):
    return config_from_args(build_parser().parse_args(["fit", "s.xml", *args]))


def test_no_flags_give_the_config_defaults():
    assert parse() == FitConfig()


def test_every_flag_sets_its_field():
    defaults = FitConfig()
    for flag, name, _, opts in FLAGS:
        default = getattr(defaults, name)
        if isinstance(default, bool):
            cfg = parse(flag)
        elif "choices" in opts:
            cfg = parse(flag, [c for c in opts["choices"] if c != default][0])
        elif name == "weights":
            cfg = parse(flag, "rgb2lidar=0")
        elif name in ("output", "render_samples"):
            cfg = parse(flag, "7")
        elif name == "densify_fraction":
            cfg = parse(flag, "0.05")
        else:
            cfg = parse(flag, str(default + 1))
        changed = [f.name for f in dataclasses.fields(cfg) if getattr(cfg, f.name) != getattr(defaults, f.name)]
        assert changed == [name], (flag, changed)


@pytest.mark.parametrize("args, message", [
    (["--width", "0"], "--width must be positive"),
    (["--render-samples", "some"], "--render-samples must be 'auto' or a positive number"),
    (["--weights", "nosuch=1"], "--weights"),
    (["--bounces", "-1"], "--bounces must be in 0..8"),
    (["--bounces", "9"], "--bounces must be in 0..8"),
    (["--sky-patterns", "0"], "--sky-patterns must be positive"),
    (["--range-weight", "-1"], "--range-weight must be in 0.."),
    (["--range-weight", "nan"], "--range-weight must be in 0.."),
    (["--densify-fraction", "1.5"], "--densify-fraction must be in 0..1"),
    (["--densify-fraction", "nan"], "--densify-fraction must be in 0..1"),
])
def test_bad_values_are_refused(args, message):
    with pytest.raises(UserError, match=message):
        parse(*args)
