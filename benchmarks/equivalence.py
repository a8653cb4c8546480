"""Is training bit-identical to another revision? Same seeded tiny ``learn`` runs here and at a git ref, compared.

``python -m benchmarks.equivalence --ref main`` runs every case of ``benchmarks/_equivalence_cases.py`` (Mlp, Cnn and
MultiInput policies, Discrete and Box actions, 1-3 levels, the shared world model, subgoal updates in imagination,
with and without the replay context, RSSM with the reference-compat switches) once with this working tree's
``sb3_hieros`` and once with the one of ``--ref`` (checked out into a temporary git worktree, removed afterwards),
each in a fresh interpreter on one torch thread. Per case it prints whether the parameters and buffers, the
optimiser states, the counters (steps, updates per level), the replay of every level, a prediction after training and
the global random states are identical, and names what differs. The models trained at the ref are also saved and
loaded here: their parameters, optimiser states, counters and predictions must match too. The exit code is 1 if any
case differs or fails.

Both sides build their models with ``preset``, ``config_overrides`` and SB3's standard keywords only, so the cases
run on revisions with other constructor keywords; parameter and optimiser names are compared without a
``hierarchy`` path segment.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
from collections.abc import Mapping, Sequence
from typing import Any

from benchmarks import _gitref
from benchmarks._equivalence_cases import CASES

__all__ = ["CASES_SCRIPT", "compare", "fingerprints", "main"]

CASES_SCRIPT = pathlib.Path(__file__).resolve().parent / "_equivalence_cases.py"
#: The parts of a fingerprint, in the order they are reported.
PARTS = ("params", "optimizers", "counters", "replay", "predict", "rng")


def _case_names() -> list[str]:
    return sorted(CASES)


def fingerprints(
    root: pathlib.Path,
    cases: Sequence[str],
    steps: int,
    timeout: float | None = None,
    save_dir: pathlib.Path | None = None,
    load_dir: pathlib.Path | None = None,
) -> dict[str, Any]:
    """Run the cases with the ``sb3_hieros`` of the tree at ``root`` in a fresh interpreter.

    :param root: a tree of this repository (the working tree or a temporary checkout)
    :param cases: case names
    :param steps: environment steps of ``learn`` per case
    :param timeout: seconds for all cases together, or None
    :param save_dir: also save every trained model there
    :param load_dir: instead of training, load the models saved there and fingerprint them
    :return: case -> fingerprint (or ``{"error": ...}``)
    """
    with tempfile.TemporaryDirectory(prefix="sb3-hieros-equivalence-") as tmp:
        out = pathlib.Path(tmp) / "fingerprints.json"
        args = ["--out", str(out), "--steps", str(steps), "--cases", *cases]
        args += [] if save_dir is None else ["--save-dir", str(save_dir)]
        args += [] if load_dir is None else ["--load-dir", str(load_dir)]
        result = _gitref.run_script(root, CASES_SCRIPT, args, timeout=timeout)
        if result.returncode != 0 or not out.exists():
            raise RuntimeError(f"the cases failed to run with {root}/sb3_hieros:\n{result.stderr[-4000:]}")
        found = json.loads(out.read_text())
    for name, fingerprint in found.items():
        origin = fingerprint.get("sb3_hieros")
        if origin is not None and not pathlib.Path(origin).resolve().is_relative_to(root.resolve()):
            raise RuntimeError(f"case {name} imported sb3_hieros from {origin}, not from {root}")
    return found


def _differences(here: Mapping[str, Any], there: Mapping[str, Any]) -> list[str]:
    """What differs between two fingerprints of one case, one phrase per differing part."""
    out = []
    for part in PARTS:
        a, b = here.get(part), there.get(part)
        if a == b:
            continue
        if part == "counters":
            out.append(f"{part}: {a} here, {b} at the ref")
        elif isinstance(a, Mapping) and isinstance(b, Mapping):
            names = sorted(set(a) | set(b))
            changed = [n for n in names if a.get(n) != b.get(n)]
            shown = ", ".join(changed[:3]) + (", ..." if len(changed) > 3 else "")
            out.append(f"{part}: {len(changed)} of {len(names)} differ ({shown})")
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            out.append(f"{part}: levels {[i for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y]} differ")
        else:
            out.append(part)
    return out


def compare(here: Mapping[str, Any], there: Mapping[str, Any]) -> tuple[list[str], bool]:
    """Report lines per case and whether every case is identical.

    :param here: fingerprints of the working tree
    :param there: fingerprints of the ref
    :return: (lines, all identical)
    """
    lines, same = [], True
    for name in sorted(set(here) | set(there)):
        a, b = here.get(name), there.get(name)
        if a is None or b is None:
            lines.append(f"{name}: missing {'here' if a is None else 'at the ref'}")
            same = False
        elif "error" in a or "error" in b:
            errors = [f"{side}: {fp['error']}" for side, fp in (("here", a), ("ref", b)) if "error" in fp]
            lines.append(f"{name}: FAILED ({'; '.join(errors)})")
            same = False
        else:
            diffs = _differences(a, b)
            n_params = len(a.get("params", {}))
            if diffs:
                lines.append(f"{name}: DIFFERENT - " + "; ".join(diffs))
                same = False
            else:
                lines.append(f"{name}: identical ({n_params} tensors, {len(a.get('optimizers', {}))} optimisers)")
    return lines, same


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point (see the module docstring).

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: exit code, 0 when every case is identical
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", required=True, help="git revision to compare with (branch, tag or commit)")
    parser.add_argument("--cases", nargs="+", default=None, help="case names (default: all); --list shows them")
    parser.add_argument("--list", action="store_true", help="print the case names and exit")
    parser.add_argument("--steps", type=int, default=64, help="environment steps of learn per case (default 64)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per side (default 1800)")
    args = parser.parse_args(argv)
    names = _case_names()
    if args.list:
        print("\n".join(names))
        return 0
    cases = names if args.cases is None else list(args.cases)
    unknown = sorted(set(cases) - set(names))
    if unknown:
        parser.error(f"unknown cases {unknown}; the cases are {names}")
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    try:
        commit = _gitref.resolve(args.ref)
    except ValueError as error:
        parser.error(str(error))
    root = _gitref.repo_root()
    print(f"working tree {root} against {args.ref} ({commit[:12]}): {len(cases)} cases, {args.steps} steps each")
    here = fingerprints(root, cases, args.steps, args.timeout)
    with tempfile.TemporaryDirectory(prefix="sb3-hieros-saves-") as saves:
        with _gitref.checkout(commit, root) as tree:
            there = fingerprints(tree, cases, args.steps, args.timeout, save_dir=pathlib.Path(saves))
        loaded = fingerprints(root, cases, args.steps, args.timeout, load_dir=pathlib.Path(saves))
    lines, same = compare(here, there)
    print("\n".join(lines))
    saved = {name: {k: v for k, v in fp.items() if k not in ("replay", "rng")} for name, fp in there.items()}
    load_lines, load_same = compare(loaded, saved)
    print(f"models saved at {args.ref}, loaded here:")
    print("\n".join("  " + line for line in load_lines))
    print("all identical" if same and load_same else "NOT identical")
    return 0 if same and load_same else 1


if __name__ == "__main__":
    sys.exit(main())
