"""Output folders: the one place that decides where a command may write.

Every command that writes results (``import``, ``fit``, ``eval``, ``render``,
``relight``, ``night``, ``insert``, ``lidar``, ``make-scene``) goes through
this module, so that no command can delete or overwrite a file it did not
write:

* An output folder must be new, empty, or one that mi-invrgbl wrote. Such a
  folder carries a marker file :data:`MARKER` (JSON: the command, the tool's
  version, the command line and the list of files the command wrote).
* The current folder, every input, and every folder that holds an input or
  the current folder are refused as outputs, with or without ``--overwrite``.
* A folder written by another command is refused (``relight -o FIT_DIR``
  would replace the fit). A folder written by the same command is replaced
  only with ``--overwrite`` (``import``, ``fit``) or by default for the
  commands whose results are cheap to make again (``render``, ``relight``,
  ``night``, ``insert``, ``lidar``); ``fit --resume`` continues one.
* Replacing replaces only the files the marker lists. Anything else found in
  the folder (a user's notes, a ``fit/`` folder inside an import folder) is
  kept, byte for byte.
* Results are written into a temporary sibling folder
  (``.NAME.partial-XXXX``) and renamed into place when the command finishes,
  so an interrupted run leaves the old folder untouched (and at most a hidden
  ``.partial`` folder beside it), never a mix of old and new files.
* The temporary folder is marked at once (command and process id): a second
  run into the same output is refused while the first one writes, and the
  folder of a run that was killed is reported by the next run and continued
  by ``fit --resume``.

Use::

    out = prepare(target, "relight", inputs=[scene_xml], replace_own=True)
    try:
        ... write everything into out.path ...
    except BaseException:
        out.discard()
        raise
    out.commit()

Single files that a command updates in place (``eval``'s ``metrics.json``)
go through :func:`write_file`, which allows replacing a file only when a
marker lists it (or its content shows that mi-invrgbl wrote it).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserError

#: Name of the marker file in every folder mi-invrgbl writes.
MARKER = ".mi-invrgbl"
#: Marker format tag.
FORMAT = "mi-invrgbl-output/1"
#: Command line recorded in markers; set by :func:`mi_invrgbl.cli.main`.
command_line: list[str] = []


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def atomic_write(path, write) -> Path:
    """Write one file so that a reader never sees it half written.

    ``write(tmp)`` writes the content to a temporary path beside ``path``
    (same folder, so the rename cannot cross file systems; same extension, so
    writers that pick the format from it, Mitsuba's bitmaps and ``np.savez``,
    write the right one); it is then renamed over ``path``. The temporary
    file is created new (``mkstemp``), so a file of the user's that happens
    to have a temporary-looking name is never written over. The folder is
    created if missing. If ``write`` fails the temporary file is removed and
    ``path`` keeps its old content. The package's file writers all use it;
    a whole output folder is, besides, staged and renamed by :func:`prepare`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".part" + path.suffix,
                                dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        # mkstemp makes it private (0600); the result gets the usual mode.
        os.chmod(tmp, 0o666 & ~_UMASK)
        write(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise
    return path


def atomic_write_text(path, text: str) -> Path:
    """:func:`atomic_write` of a text (UTF-8)."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def _version() -> str:
    try:
        from . import __version__
        return __version__
    except ImportError:      # the package's __init__ needs a Mitsuba variant
        return "unknown"


# ----------------------------------------------------------------------------
# The marker
# ----------------------------------------------------------------------------
@dataclass
class Marker:
    """What :data:`MARKER` records about a folder."""
    command: str | None          # the command that wrote the folder; None: files only
    files: list[str]             # paths relative to the folder, '/'-separated
    complete: bool = True        # False: an interrupted run's results
    version: str = ""
    command_line: list[str] = field(default_factory=list)
    written: str = ""
    pid: int = 0                 # a temporary folder's: the process writing it

    def to_json(self) -> str:
        data = {"format": FORMAT, "tool": "mi-invrgbl", "version": self.version,
                "command": self.command, "command_line": self.command_line,
                "complete": self.complete, "written": self.written, "files": sorted(self.files)}
        if self.pid:
            data["pid"] = self.pid
        return json.dumps(data, indent=1)


def read_marker(folder) -> Marker | None:
    """The marker of ``folder``, or None when it has none (or an unreadable one)."""
    path = Path(folder) / MARKER
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        return None
    files = data.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return Marker(command=data.get("command"), files=list(files),
                  complete=bool(data.get("complete", True)), version=str(data.get("version", "")),
                  command_line=list(data.get("command_line") or []),
                  written=str(data.get("written", "")), pid=int(data.get("pid") or 0))


def _write_marker(folder: Path, marker: Marker) -> None:
    marker.version = marker.version or _version()
    marker.written = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    atomic_write_text(folder / MARKER, marker.to_json())


def _files_under(folder: Path) -> list[str]:
    """Every file (and symlink, and empty folder) under ``folder``, relative, without the marker."""
    out = []
    for root, dirs, files in os.walk(folder):
        rel_root = os.path.relpath(root, folder)
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            rel = name if rel_root == "." else os.path.join(rel_root, name)
            if rel != MARKER:
                out.append(rel.replace(os.sep, "/"))
        if not files and not dirs and rel_root != ".":
            out.append(rel_root.replace(os.sep, "/") + "/")
    return sorted(out)


def mark(folder, command: str, complete: bool = True) -> Marker:
    """Write the marker of a folder that ``command`` has just written in full."""
    folder = Path(folder)
    marker = Marker(command=command, files=_files_under(folder), complete=complete,
                    command_line=list(command_line))
    _write_marker(folder, marker)
    return marker


# ----------------------------------------------------------------------------
# Checks
# ----------------------------------------------------------------------------
def _real(path) -> Path:
    return Path(os.path.realpath(os.path.abspath(path)))


def _is_within(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def _check_not_input(target: Path, inputs, what: str) -> None:
    real = _real(target)
    cwd = _real(os.getcwd())
    if real == cwd:
        raise UserError("%s: %s is the current folder; choose a new folder" % (target, what))
    if _is_within(cwd, real):
        raise UserError("%s: %s holds the current folder; choose a new folder" % (target, what))
    for item in inputs or ():
        if item is None:
            continue
        inp = _real(item)
        if real == inp:
            raise UserError("%s: %s is an input of this command; choose a new folder"
                            % (target, what))
        if _is_within(inp, real):
            raise UserError("%s: %s holds the input %s; choose a new folder"
                            % (target, what, item))


def _describe(marker: Marker) -> str:
    if marker.command == "fit":
        return "a finished fit" if marker.complete else "an interrupted fit"
    return "the results of 'mi-invrgbl %s'" % marker.command


def _alive(pid: int) -> bool:
    if pid <= 0 or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def leftovers(target, command: str) -> list:
    """Temporary folders of ``command`` beside ``target`` whose process is gone
    (a run killed before it could clean up), newest first. Raises when a live
    process is still writing one: two runs must not write the same folder."""
    target = Path(os.path.abspath(target))
    found = []
    if not target.parent.is_dir():
        return found
    for p in target.parent.glob(".%s.partial-*" % target.name):
        marker = read_marker(p) if p.is_dir() and not p.is_symlink() else None
        if marker is None or marker.command != command:
            continue
        if _alive(marker.pid):
            raise UserError("%s: another 'mi-invrgbl %s' (process %d) is writing this folder; "
                            "wait for it to finish or choose another folder"
                            % (target, command, marker.pid))
        found.append(p)
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


def _check_writable(folder: Path) -> list:
    """Create ``folder`` (and its parents) if needed and check that files can be made
    in it; returns the folders it created, deepest first."""
    created, p = [], folder
    while not p.exists() and p != p.parent:
        created.append(p)
        p = p.parent
    if not p.is_dir():
        raise UserError("%s: not a folder, cannot hold the output" % p)
    if not os.access(p, os.W_OK | os.X_OK):
        raise UserError("%s: cannot write here (permission denied)" % p)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError("%s: cannot create the output's parent folder (%s)"
                        % (folder, exc.strerror or exc)) from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UserError("%s: cannot write here (permission denied)" % folder)
    return created


def _remove_empty(folders) -> None:
    for d in folders:
        try:
            d.rmdir()
        except OSError:
            return


# ----------------------------------------------------------------------------
# Output folders
# ----------------------------------------------------------------------------
class OutputFolder:
    """A command's output folder: write into :attr:`path`, then :meth:`commit`.

    ``path`` is a temporary sibling of ``target``; :meth:`commit` renames it
    into place (keeping files of the old folder that the tool did not write),
    :meth:`discard` removes it.
    """

    def __init__(self, target: Path, staging: Path, command: str, previous: Marker | None,
                 created=()):
        self.target = target
        self.created = list(created)
        self.path = staging
        self.command = command
        self.previous = previous
        self.done = False

    def __repr__(self):
        return "OutputFolder(%s -> %s)" % (self.path, self.target)

    def log(self, text: str) -> None:
        """Print a progress line, naming the final folder rather than the temporary one."""
        print(str(text).replace(str(self.path), str(self.target)))

    def discard(self) -> None:
        """Remove the temporary folder (only this object created it)."""
        if not self.done:
            shutil.rmtree(self.path, ignore_errors=True)
            _remove_empty(self.created)
            self.done = True

    def commit(self, complete: bool = True) -> Path:
        """Move the results into ``target``; returns ``target``."""
        if self.done:
            raise RuntimeError("output folder already committed or discarded")
        mark(self.path, self.command, complete)      # replaces the temporary marker (no pid)
        target = self.target
        if not target.exists():
            os.rename(self.path, target)
        elif target.is_dir() and not any(target.iterdir()):
            os.rmdir(target)
            os.rename(self.path, target)
        else:
            self._replace(target)
        self.done = True
        return target

    def _replace(self, target: Path) -> None:
        old = read_marker(target)
        if old is None or old.command != self.command:
            # Checked in prepare(); someone changed the folder meanwhile.
            raise UserError("%s: was changed while this command ran and is no longer its "
                            "output folder; the results are in %s" % (target, self.path))
        owned = set(old.files)
        keep = [f for f in _files_under(target) if f not in owned]
        clash = [f for f in keep if (self.path / f.rstrip("/")).exists()
                 and not f.endswith("/")]
        if clash:
            raise UserError("%s: was not written by mi-invrgbl and the new results have a file "
                            "of that name; move it away (the results are in %s)"
                            % (target / clash[0], self.path))
        trash = Path(tempfile.mkdtemp(prefix=".%s.old-" % target.name, dir=target.parent))
        old_dir = trash / "old"
        os.rename(target, old_dir)
        try:
            os.rename(self.path, target)
        except OSError:
            os.rename(old_dir, target)
            raise
        # Files the tool did not write go back where they were.
        for rel in keep:
            src, dst = old_dir / rel.rstrip("/"), target / rel.rstrip("/")
            dst.parent.mkdir(parents=True, exist_ok=True)
            if rel.endswith("/"):
                dst.mkdir(exist_ok=True)
            else:
                os.rename(src, dst)
        # Of the old folder only files the marker lists are deleted.
        for rel in list(owned) + [MARKER]:
            p = old_dir / rel
            if p.is_symlink() or p.is_file():
                p.unlink()
        for root, dirs, _ in os.walk(old_dir, topdown=False):
            for d in dirs:
                try:
                    os.rmdir(os.path.join(root, d))
                except OSError:
                    pass
        try:
            os.rmdir(old_dir)
            os.rmdir(trash)
        except OSError:
            warnings.warn("%s: kept what could not be put back into %s" % (trash, target),
                          UserWarning, stacklevel=2)


def prepare(target, command: str, inputs=(), overwrite: bool = False, resume: bool = False,
            replace_own: bool = False, what: str = "the output folder") -> OutputFolder:
    """Check ``target`` as ``command``'s output folder and open a temporary one beside it.

    Parameters
    ----------
    target : path
        The output folder the results should end up in.
    command : str
        The command writing it (recorded in the marker).
    inputs : paths
        Files and folders the command reads; none of them, nor a folder
        holding one, may be the output.
    overwrite : bool
        Replace ``command``'s own earlier results in ``target``.
    resume : bool
        Continue ``command``'s results in ``target``: the temporary folder
        starts as a copy of the files the marker lists.
    replace_own : bool
        Replace ``command``'s own earlier results even without ``overwrite``.
    """
    target = Path(os.path.abspath(target))
    _check_not_input(target, inputs, what)
    previous = None
    if target.is_symlink():
        raise UserError("%s: %s is a symbolic link; give the folder itself" % (target, what))
    if target.exists():
        if not target.is_dir():
            raise UserError("%s: %s exists and is not a folder" % (target, what))
        if any(target.iterdir()):
            previous = read_marker(target)
            if previous is None or previous.command is None:
                raise UserError("%s: %s is not empty and was not written by mi-invrgbl "
                                "(no %s marker); choose a new or empty folder"
                                % (target, what, MARKER))
            if previous.command != command:
                raise UserError("%s: %s holds %s; choose another folder"
                                % (target, what, _describe(previous)))
            if not (overwrite or resume or replace_own):
                hint = ("pass --resume to continue it or --overwrite to replace it"
                        if command == "fit" else "pass --overwrite to replace it")
                raise UserError("%s: %s holds %s; %s (only the files mi-invrgbl wrote are "
                                "replaced) or choose a new folder"
                                % (target, what, _describe(previous), hint))
            if not os.access(target, os.W_OK | os.X_OK):
                raise UserError("%s: cannot replace the files in %s (permission denied)"
                                % (target, what))
    stale = leftovers(target, command)
    if resume and stale and (previous is None or not (target / MARKER).exists()
                             or stale[0].stat().st_mtime > (target / MARKER).stat().st_mtime):
        # A run killed without cleaning up: its temporary folder is newer
        # than the results; continue from it.
        staging = stale[0]
        _write_marker(staging, Marker(command=command, files=[], complete=False,
                                      command_line=list(command_line), pid=os.getpid()))
        warnings.warn("%s: continuing from %s, left by a run that was killed"
                      % (target, staging.name), UserWarning, stacklevel=2)
        return OutputFolder(target, staging, command, previous)
    if resume and previous is None:
        raise UserError("%s: nothing to resume (no results of 'mi-invrgbl %s' there)"
                        % (target, command))
    for p in stale:
        warnings.warn("%s: left by a run of 'mi-invrgbl %s' that was killed%s; remove it when "
                      "it is not needed" % (p, command, " (--resume continues from it)"
                                            if command == "fit" else ""),
                      UserWarning, stacklevel=2)
    parent = target.parent
    created = _check_writable(parent)
    try:
        staging = Path(tempfile.mkdtemp(prefix=".%s.partial-" % target.name, dir=parent))
    except OSError as exc:
        _remove_empty(created)
        raise UserError("%s: cannot write here (%s)" % (parent, exc.strerror or exc)) from None
    # mkdtemp makes the folder private (0700); results get the usual mode.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(staging, 0o777 & ~umask)
    # Marked at once: a run killed later leaves a folder recognisable as this
    # command's (and a live run's folder is not taken by a second one).
    _write_marker(staging, Marker(command=command, files=[], complete=False,
                                  command_line=list(command_line), pid=os.getpid()))
    out = OutputFolder(target, staging, command, previous, created)
    if resume:
        try:
            for rel in previous.files:
                src = target / rel
                if src.is_file():
                    (staging / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(src, staging / rel)
        except OSError as exc:
            out.discard()
            raise UserError("%s: cannot copy the results to resume from (%s)"
                            % (target, exc.strerror or exc)) from None
    return out


def add_overwrite_option(parser) -> None:
    """``--overwrite`` for a command's argument parser (one wording everywhere)."""
    parser.add_argument("--overwrite", action="store_true",
                        help="replace this command's earlier results in the output folder "
                             "(only the files it wrote; anything else there is kept)")


def staged(target, command: str, inputs=(), overwrite: bool = False, **kwargs):
    """Context manager around :func:`prepare`: yields the :class:`OutputFolder`,
    commits it when the block finishes, discards it when the block raises."""
    return _Staged(prepare(target, command, inputs, overwrite, **kwargs))


class _Staged:
    def __init__(self, out: OutputFolder):
        self.out = out

    def __enter__(self) -> OutputFolder:
        return self.out

    def __exit__(self, kind, value, tb):
        if kind is None:
            if not self.out.done:
                self.out.commit()
        else:
            self.out.discard()
        return False


def check_new_folder(target, command: str, inputs=(), what: str = "the output folder") -> Path:
    """Check a folder a command creates itself (it must not exist, or be empty)."""
    target = Path(os.path.abspath(target))
    _check_not_input(target, inputs, what)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise UserError("%s: %s already exists; choose a new folder" % (target, what))
    _check_writable(target.parent)
    return target


# ----------------------------------------------------------------------------
# Single files
# ----------------------------------------------------------------------------
def check_file(path, command: str, inputs=(), recognise=None, what: str = "output file") -> Path:
    """Check that ``command`` may write ``path``: a new file, or one mi-invrgbl wrote.

    A file counts as mi-invrgbl's when the marker of its folder lists it, or
    when ``recognise(path)`` says so (files written before markers existed).
    """
    path = Path(os.path.abspath(path))
    for item in inputs or ():
        if item is not None and _real(item) == _real(path):
            raise UserError("%s: the %s is an input of this command" % (path, what))
    if path.is_dir():
        raise UserError("%s: the %s is a folder" % (path, what))
    if path.exists():
        marker = read_marker(path.parent)
        listed = marker is not None and path.name in marker.files
        if not listed and not (recognise is not None and recognise(path)):
            raise UserError("%s: exists and was not written by mi-invrgbl; choose another %s"
                            % (path, what))
    _check_writable(path.parent)
    return path


def write_file(path, data, command: str, inputs=(), recognise=None,
               what: str = "output file") -> Path:
    """Write ``data`` (str or bytes) to ``path`` atomically after :func:`check_file`,
    and list it in its folder's marker."""
    path = check_file(path, command, inputs, recognise, what)
    try:
        if isinstance(data, bytes):
            atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
        else:
            atomic_write_text(path, data)
    except OSError as exc:
        raise UserError("%s: cannot write (%s)" % (path, exc.strerror or exc)) from None
    register_file(path)
    return path


def register_file(path) -> None:
    """List ``path`` in its folder's marker (making a files-only marker if there is none)."""
    path = Path(os.path.abspath(path))
    marker = read_marker(path.parent)
    if marker is None:
        marker = Marker(command=None, files=[], command_line=list(command_line))
    if path.name not in marker.files:
        marker.files.append(path.name)
        try:
            _write_marker(path.parent, marker)
        except OSError as exc:
            print("mi-invrgbl: warning: %s: cannot record the file in %s (%s)"
                  % (path, MARKER, exc.strerror or exc), file=sys.stderr)
