"""Run a script of this working tree against the ``sb3_hieros`` package of another git revision.

:func:`checkout` puts a revision of this repository into a temporary directory (``git worktree add --detach``) and
removes it afterwards; :func:`run_script` runs a Python file in a fresh interpreter whose ``sys.path`` starts with a
given tree, so that ``import sb3_hieros`` there loads that tree's package. ``benchmarks/equivalence.py`` uses both to
compare the working tree with a revision; a speed comparison can do the same.
"""

from __future__ import annotations

import contextlib
import pathlib
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence

__all__ = ["checkout", "repo_root", "resolve", "run_script"]

# Runs sys.argv[2] as __main__ with sys.argv[1] first on sys.path and sys.argv[3:] as its arguments.
_BOOTSTRAP = (
    "import runpy, sys; root, script = sys.argv[1], sys.argv[2]; sys.path.insert(0, root); "
    "sys.argv = sys.argv[2:]; runpy.run_path(script, run_name='__main__')"
)


def _git(args: Sequence[str], cwd: pathlib.Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=False)


def repo_root(start: pathlib.Path | None = None) -> pathlib.Path:
    """The top directory of the git working tree that holds ``start`` (default: this file).

    :param start: a path inside the working tree
    :return: its root
    """
    here = pathlib.Path(__file__).resolve().parent if start is None else pathlib.Path(start).resolve()
    result = _git(["rev-parse", "--show-toplevel"], here)
    if result.returncode != 0:
        raise ValueError(f"{here} is not inside a git working tree: {result.stderr.strip()}")
    return pathlib.Path(result.stdout.strip())


def resolve(ref: str, root: pathlib.Path | None = None) -> str:
    """The commit hash ``ref`` names in the repository of ``root``.

    :param ref: a branch, tag, commit or any other revision git understands
    :param root: the working tree (default: this one)
    :return: 40 hex digits
    """
    if not isinstance(ref, str) or not ref or ref.startswith("-"):
        raise ValueError(f"ref must be a git revision such as a branch name or a commit, got {ref!r}")
    root = repo_root() if root is None else root
    result = _git(["rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"], root)
    if result.returncode != 0:
        raise ValueError(f"{ref!r} names no commit of the repository at {root}")
    return result.stdout.strip()


@contextlib.contextmanager
def checkout(ref: str, root: pathlib.Path | None = None) -> Iterator[pathlib.Path]:
    """A temporary detached working tree of ``ref``, removed (with its git bookkeeping) on exit.

    :param ref: the revision
    :param root: the working tree whose repository holds ``ref`` (default: this one)
    :return: context manager yielding the temporary tree's root
    """
    root = repo_root() if root is None else root
    commit = resolve(ref, root)
    parent = pathlib.Path(tempfile.mkdtemp(prefix="sb3-hieros-ref-"))
    tree = parent / "tree"
    added = _git(["worktree", "add", "--detach", "--quiet", str(tree), commit], root)
    if added.returncode != 0:
        shutil.rmtree(parent, ignore_errors=True)
        raise RuntimeError(f"git worktree add of {ref} ({commit[:12]}) failed: {added.stderr.strip()}")
    try:
        yield tree
    finally:
        _git(["worktree", "remove", "--force", str(tree)], root)
        shutil.rmtree(parent, ignore_errors=True)
        _git(["worktree", "prune"], root)


def run_script(
    source_root: pathlib.Path, script: pathlib.Path, args: Sequence[str] = (), timeout: float | None = None
) -> subprocess.CompletedProcess[str]:
    """Run the Python file ``script`` as ``__main__`` in a fresh interpreter with ``source_root`` first on sys.path.

    The interpreter is this one (same virtual environment); stdout and stderr are captured.

    :param source_root: the tree whose ``sb3_hieros`` is to be imported
    :param script: the file to run (it may lie in another tree)
    :param args: its command-line arguments
    :param timeout: seconds before the run is killed, or None
    :return: the finished process
    """
    command = [sys.executable, "-c", _BOOTSTRAP, str(source_root), str(script), *map(str, args)]
    return subprocess.run(command, cwd=source_root, capture_output=True, text=True, timeout=timeout, check=False)
