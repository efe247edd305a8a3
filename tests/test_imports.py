"""Imports run one way: from the command line down to the physics.

Every module of the package is read with ``ast`` (nothing is imported) and
mapped to a layer; an import of a module in a higher layer, or in another
part of the same layer, fails the test with the module and the import named.

Layers, top to bottom (a module may import its own part and any lower layer):

=====  ==========================================================  ==============================
rank   part (modules)                                              job
=====  ==========================================================  ==============================
6      ``commands``: ``cli``, ``commands.*``                       the ``mi-invrgbl`` command
5      ``fit``, ``apps``, ``synthetic``, ``importer``              the jobs the commands run:
       (``io.importer``)                                           inverse rendering, the
                                                                   applications, the generator,
                                                                   the import of a drive
4      ``eval``                                                    metrics and scoring (the fit
                                                                   scores held-out frames with
                                                                   the same metrics)
3      ``scene``, ``io`` (all of ``io`` but ``io.importer``)       what a scene is (frames.json,
                                                                   posing, loading, XML); data
                                                                   readers and writers
2      ``plugins``                                                 the Mitsuba plugins
1      ``physics``                                                 shared physics under the plugins
0      ``base``: the package itself, ``errors``, ``variant``,       importable from anywhere
       ``outdir`` (output folders)
=====  ==========================================================  ==============================

``io.importer`` sits with the jobs, above ``io``: it composes the readers, the
scene records and the scene XML into an imported scene.

:data:`PENDING` lists imports that wait for a move already decided (each
with where the code goes); the test fails as soon as one is no longer made,
so that the entry is deleted with the move.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "mi_invrgbl"

#: (module prefix, part, rank); the longest matching prefix wins.
LAYERS = (
    ("mi_invrgbl.cli", "commands", 6),
    ("mi_invrgbl.commands", "commands", 6),
    ("mi_invrgbl.fit", "fit", 5),
    ("mi_invrgbl.apps", "apps", 5),
    ("mi_invrgbl.synthetic", "synthetic", 5),
    ("mi_invrgbl.io.importer", "importer", 5),
    ("mi_invrgbl.eval", "eval", 4),
    ("mi_invrgbl.scene", "scene", 3),
    ("mi_invrgbl.io", "io", 3),
    ("mi_invrgbl.plugins", "plugins", 2),
    ("mi_invrgbl.physics", "physics", 1),
    ("mi_invrgbl.errors", "base", 0),
    ("mi_invrgbl.variant", "base", 0),
    ("mi_invrgbl.outdir", "base", 0),
    ("mi_invrgbl", "base", 0),          # the package's __init__ only: a new module needs a row
)


#: (importing module, imported module) -> the move that removes the import.
PENDING: dict = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer(module: str):
    best = None
    for prefix, part, rank in LAYERS:
        if module == prefix or (module.startswith(prefix + ".") and prefix != "mi_invrgbl"):
            if best is None or len(prefix) > len(best[0]):
                best = (prefix, part, rank)
    return None if best is None else best[1:]


def imports(path: Path):
    """(line, imported module) of every import of the package in ``path``,
    wherever it sits (top level or inside a function)."""
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "mi_invrgbl":
                    yield node.lineno, alias.name, False
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.split(".")[0] == "mi_invrgbl":
                target = node.module
            else:
                continue
            if node.module is None:       # from . import a, b: each a module or a name
                for alias in node.names:
                    yield node.lineno, target + "." + alias.name, True
            else:
                yield node.lineno, target, False


def package_modules():
    return sorted(PACKAGE.rglob("*.py"))


def violations():
    out = []
    for path in package_modules():
        source = module_name(path)
        src_part, src_rank = layer(source)
        for line, target, _ in imports(path):
            found = layer(target)
            if found is None or (source, target) in PENDING:
                continue
            part, rank = found
            where = "%s (%s:%d) imports %s" % (source, path.relative_to(PACKAGE.parent), line, target)
            if rank > src_rank:
                out.append("%s: %s (rank %d) is above %s (rank %d)"
                           % (where, part, rank, src_part, src_rank))
            elif rank == src_rank and part != src_part and part != "base":
                out.append("%s: %s and %s are parts of one layer and must not import each other"
                           % (where, src_part, part))
    return out


def test_every_module_has_a_layer():
    unmapped = [module_name(p) for p in package_modules() if layer(module_name(p)) is None]
    assert not unmapped, unmapped


def test_imports_run_downward_only():
    found = violations()
    assert not found, "upward or sideways imports:\n" + "\n".join(found)


def test_pending_moves_are_still_pending():
    made = {(module_name(p), target) for p in package_modules() for _, target, _ in imports(p)}
    done = [pair for pair in PENDING if pair not in made]
    assert not done, "no longer imported, delete from PENDING: %s" % done


@pytest.mark.parametrize("module, text, expected", [
    ("mi_invrgbl.scene.frames", "from ..commands.render_sensors import load_scene\n",
     "is above scene"),
    ("mi_invrgbl.apps.frame_set", "from ..synthetic.trajectory import KITTI_FROM_MITSUBA\n",
     "apps and synthetic are parts of one layer"),
    ("mi_invrgbl.physics.brdf", "def f():\n    import mi_invrgbl.plugins.gaussians\n",
     "is above physics"),
    ("mi_invrgbl.io.kitti", "from . import importer\n", "is above io"),
])
def test_the_check_sees_a_wrong_import(tmp_path, monkeypatch, module, text, expected):
    """The walker finds upward imports in every form (relative, absolute,
    inside a function, ``from . import module``)."""
    fake = tmp_path / "mi_invrgbl"
    path = fake.joinpath(*module.split(".")[1:]).with_suffix(".py")
    path.parent.mkdir(parents=True)
    path.write_text(text)
    monkeypatch.setitem(globals(), "PACKAGE", fake)
    found = violations()
    assert len(found) == 1 and expected in found[0] and module in found[0], found


def _module_exists(name: str) -> bool:
    base = PACKAGE.joinpath(*name.split(".")[1:])
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def missing_modules():
    """Imports of package modules that do not exist (a module moved and an
    import left behind, often inside a function where nothing runs it)."""
    out = []
    for path in package_modules():
        for line, target, maybe_name in imports(path):
            # ``from . import a``: ``a`` may be a name of the package, not a module.
            if _module_exists(target) or (maybe_name and _module_exists(target.rpartition(".")[0])):
                continue
            out.append("%s (%s:%d) imports %s, which does not exist"
                       % (module_name(path), path.relative_to(PACKAGE.parent), line, target))
    return out


def test_every_imported_module_exists():
    found = missing_modules()
    assert not found, "\n".join(found)


def test_the_check_sees_a_missing_module(tmp_path, monkeypatch):
    fake = tmp_path / "mi_invrgbl"
    (fake / "fit").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / "fit" / "__init__.py").write_text("")
    (fake / "fit" / "a.py").write_text("def f():\n    from ..scene_graph import Frames\n")
    monkeypatch.setitem(globals(), "PACKAGE", fake)
    found = missing_modules()
    assert len(found) == 1 and "mi_invrgbl.scene_graph" in found[0], found
