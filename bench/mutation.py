"""Mutation testing of one estimator (or evaluation) module against its own fast tests (mutmut).

    pip install -e ".[dev]"
    nice -n 19 python -m posefuse.bench.mutation association
    python -m posefuse.bench.mutation geometry --max-children 2 \
        --tests tests/estimator/core/test_geometry.py

The module is named by its path (``estimator/translation/association.py``), its path below
``estimator/`` (``translation/association``), its import name
(``posefuse.estimator.translation.association``) or, when no other module has it, its own name
(``association``); ``evaluation/pose_error.py`` (or ``pose_error``) too. The flat names of the
layout before the paper's steps became folders still work (``estimator/geometry.py``;
``translation``, ``verification`` and ``rotation`` for the modules they became).

mutmut makes many small changes ("mutants") to the module's functions (a ``<`` for a ``<=``,
a constant plus one, an argument dropped, ...) and runs the tests that reach each changed
function: a mutant the tests fail on is *killed*; one they still pass on *survived*, so either
the tests miss a behaviour or the change is *equivalent* (no input can tell it from the
original). The score is killed / (mutants - equivalent).

The run happens in a scratch copy (``--workdir``, default
``$TMPDIR/posefuse-mutation/estimator.translation.association`` and so on):
the package laid out as ``posefuse/`` beside ``tests/``, and mutmut's own ``mutants/`` copy
inside it, so the checkout, and any process importing it, never sees a mutant. mutmut's results
stay there (``cd WORKDIR && mutmut show NAME`` prints a mutant's diff).

Equivalent mutants are listed in ``bench/mutation_equivalent.json`` by module (its path, as
``estimator/translation/association.py``), each as the function and the diff's changed lines
with a word on why no test can tell them apart, so the list survives renumbering. The command
prints killed, survived (with each diff) and equivalent, and exits 1 if a survivor is not on the
list. It is not part of the README's test command: a module takes minutes to an hour on 2 cores
(docs/testing.md has the measured runs).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EQUIVALENT_FILE = REPO / "bench" / "mutation_equivalent.json"

# the folders whose modules can be mutated
PACKAGES = ("estimator", "evaluation")
# each module's own fast tests (seconds, not minutes)
DEFAULT_TESTS = {
    "estimator/core/geometry.py": ["tests/estimator/core/test_geometry.py"],
    "estimator/core/projection.py": ["tests/estimator/core/test_geometry.py"],
    "estimator/core/symmetry.py": ["tests/estimator/core/test_symmetry.py"],
    "estimator/translation/gaussian.py": ["tests/estimator/translation/test_translation.py"],
    "estimator/translation/association.py": ["tests/estimator/translation/test_association.py"],
    "estimator/rotation/mixture.py": ["tests/estimator/rotation/test_mixture.py"],
    "estimator/verification/verify.py": ["tests/estimator/verification/test_verification.py"],
    "estimator/verification/model_edges.py": ["tests/estimator/verification/test_verification.py"],
    "estimator/verification/edge_maps.py": ["tests/estimator/verification/test_verification.py"],
    "estimator/verification/refinement.py": ["tests/estimator/verification/test_refinement.py"],
    "evaluation/pose_error.py": ["tests/evaluation/test_evaluation.py"],
}
# flat modules of the old layout that became a module of another name
RENAMED = {
    "translation": "estimator/translation/gaussian.py",
    "verification": "estimator/verification/verify.py",
    "rotation": "estimator/rotation/matching.py",
}
# what the tests read besides the package: copied next to tests/ as in the checkout
DATA_DIRS = ("catalogs", "models", "recordings")
# a mutant whose tests crash the interpreter (a segfault: e.g. OpenCV given a NaN map) failed
# them as surely as an assertion did
KILLED = ("killed", "timeout", "caught by type check", "segfault")
SKIP_TOP = {"tests", "docs", "build", "dist", "runs", "data", "out", "mutants"}


def _modules() -> list[str]:
    """Every module of PACKAGES, as its path from the checkout ('estimator/core/geometry.py')."""
    return sorted(
        p.relative_to(REPO).as_posix()
        for package in PACKAGES
        for p in (REPO / package).rglob("*.py")
        if p.name != "__init__.py" and "mutants" not in p.parts
    )


def module_path(arg: str) -> str:
    """The module's path from the checkout, from any of the names the docstring lists:
    'association', 'translation/association', 'estimator/translation/association.py' and
    'posefuse.estimator.translation.association' -> 'estimator/translation/association.py'."""
    name = arg.strip().replace("\\", "/").removesuffix(".py").removeprefix("./")
    if "/" not in name:
        name = name.replace(".", "/")
    name = name.removeprefix("posefuse/")
    if (REPO / f"{name}.py").is_file() and name.startswith(tuple(f"{p}/" for p in PACKAGES)):
        return f"{name}.py"
    name = name.removeprefix("estimator/")  # the old flat layout: estimator/geometry.py
    if name in RENAMED:
        return RENAMED[name]
    found = [m for m in _modules() if f"/{m}".removesuffix(".py").endswith(f"/{name}")]
    if len(found) == 1:
        return found[0]
    if found:
        raise SystemExit(f"{arg!r} names several modules: {', '.join(found)}")
    raise SystemExit(f"no module {arg!r} in {', '.join(f'{p}/' for p in PACKAGES)} of {REPO}")


def _listed_files() -> list[Path]:
    """The checkout's files as git sees them (tracked and untracked, not ignored)."""
    out = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "-z"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.decode()
    return [Path(p) for p in out.split("\0") if p and (REPO / p).is_file()]


def prepare(workdir: Path, module: str, tests: list[str]) -> None:
    """The scratch copy: posefuse/ (the package), tests/, the data folders, a pyproject.toml
    with mutmut's configuration for this one module."""
    if workdir.exists():
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    for rel in _listed_files():
        top = rel.parts[0]
        if top.startswith(".") or top in {"docs", "build", "dist"} or top == "node_modules":
            continue
        if "node_modules" in rel.parts:
            continue
        targets = []
        if top == "tests":
            targets.append(workdir / rel)
        else:
            if top in DATA_DIRS:
                targets.append(workdir / rel)  # tests read REPO / "catalogs" / ...
            if top not in SKIP_TOP:
                targets.append(workdir / "posefuse" / rel)
        for target in targets:
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, target)
    source = f"posefuse/{module}"
    config = {
        "source_paths": ["posefuse"],
        "only_mutate": [source],
        "also_copy": list(DATA_DIRS),
        "pytest_add_cli_args": ["-p", "no:cacheprovider", "-p", "no:randomly", "-q"],
        "pytest_add_cli_args_test_selection": tests,
        "use_git_change_detection": False,
        # a mutant that makes the tests 8x slower is counted as killed (a timeout): mostly
        # hypothesis shrinking a failure; mutmut's default of 15x doubles the run on 2 cores
        "timeout_multiplier": 8.0,
    }
    lines = ["[tool.mutmut]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in config.items()]
    lines += [
        "",
        "[tool.pytest.ini_options]",
        'testpaths = ["tests"]',
        "",
    ]
    (workdir / "pyproject.toml").write_text("\n".join(lines))


def _mutmut(workdir: Path, *args: str, capture: bool = True) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    return subprocess.run(
        [sys.executable, "-m", "mutmut", *args],
        cwd=workdir,
        env=env,
        capture_output=capture,
        text=True,
    )


def _statuses(workdir: Path, module: str) -> dict[str, str]:
    """{mutant name: status} from mutmut's own record of the run."""
    from mutmut.stats import status_by_exit_code

    meta = workdir / "mutants" / "posefuse" / f"{module}.meta"
    data = json.loads(meta.read_text())
    return {k: status_by_exit_code[v] for k, v in data["exit_code_by_key"].items()}


_DIFFS = """
import json, sys
from mutmut.mutation.diff_apply import get_diff_for_mutant
names, path = json.loads(sys.argv[1]), sys.argv[2]
print(json.dumps({n: get_diff_for_mutant(n, path=path) for n in names}))
"""


def _diffs(workdir: Path, module: str, mutants: list[str]) -> dict[str, str]:
    """{mutant: its unified diff}, all in one process (``mutmut show`` starts one per mutant)."""
    if not mutants:
        return {}
    path = f"posefuse/{module}"
    out = subprocess.run(
        [sys.executable, "-c", _DIFFS, json.dumps(mutants), path],
        cwd=workdir,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return json.loads(out)


def changed_lines(diff: str) -> list[str]:
    """The '-' and '+' lines of a unified diff, stripped: how a mutant is recognised."""
    return [
        line[0] + line[1:].strip()
        for line in diff.splitlines()
        if line[:1] in "+-" and not line.startswith(("+++", "---"))
    ]


def load_equivalent(module: str) -> list[dict]:
    """The equivalent mutants listed for ``module`` ('estimator/core/geometry.py')."""
    if not EQUIVALENT_FILE.is_file():
        return []
    return json.loads(EQUIVALENT_FILE.read_text()).get(module, [])


def function_of(mutant: str) -> str:
    """'posefuse.estimator.core.geometry.x_so3_log__mutmut_3' -> 'so3_log' (class methods too)."""
    mangled = mutant.rpartition(".")[2].partition("__mutmut_")[0]
    if mangled.startswith("x\u01c1"):  # xǁClassǁmethod
        return mangled[2:].replace("\u01c1", ".")
    return mangled.removeprefix("x_")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m posefuse.bench.mutation",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "module",
        help="association, translation/association, estimator/translation/association.py, "
        "posefuse.estimator.translation.association or evaluation/pose_error.py",
    )
    parser.add_argument("--tests", nargs="+", help="test files (default: the module's own)")
    parser.add_argument("--workdir", type=Path, help="scratch copy (default under $TMPDIR)")
    parser.add_argument("--max-children", type=int, default=1, help="parallel mutant runs")
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="print the score of the last run in WORKDIR without running",
    )
    parser.add_argument(
        "--rerun-survivors",
        action="store_true",
        help="copy the checkout's tests into WORKDIR again and re-run only the "
        "mutants that were not killed last time (after adding tests)",
    )
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args(argv)

    try:
        import mutmut  # noqa: F401
    except ImportError:
        print("mutmut is not installed: pip install -e '.[dev]'", file=sys.stderr)
        return 2
    module = module_path(args.module)
    tests = args.tests or DEFAULT_TESTS.get(module)
    if not tests:
        print(f"no default tests for {module}: pass --tests", file=sys.stderr)
        return 2
    scratch = module.removesuffix(".py").replace("/", ".")
    workdir = args.workdir or Path(tempfile.gettempdir()) / "posefuse-mutation" / scratch
    workdir = workdir.resolve()
    t0 = time.perf_counter()
    if args.rerun_survivors:
        if not (workdir / "mutants").is_dir():
            print(f"no earlier run in {workdir}", file=sys.stderr)
            return 2
        last = _statuses(workdir, module)
        again = sorted(m for m, s in last.items() if s not in KILLED)
        for dest in (workdir / "tests", workdir / "mutants" / "tests"):
            shutil.rmtree(dest)
            shutil.copytree(
                REPO / "tests", dest, ignore=shutil.ignore_patterns("node_modules", "__pycache__")
            )
        print(f"re-running {len(again)} mutants of {module}", flush=True)
        if again:
            proc = _mutmut(
                workdir, "run", "--max-children", str(args.max_children), *again, capture=False
            )
            if proc.returncode not in (0, 1):
                print(f"mutmut run exited {proc.returncode}", file=sys.stderr)
                return 2
    elif not args.report_only:
        prepare(workdir, module, tests)
        print(f"mutating {module} against {' '.join(tests)} in {workdir}", flush=True)
        proc = _mutmut(workdir, "run", "--max-children", str(args.max_children), capture=False)
        if proc.returncode not in (0, 1):
            print(f"mutmut run exited {proc.returncode}", file=sys.stderr)
            return 2
    statuses = _statuses(workdir, module)
    equivalent = load_equivalent(module)
    known = {(e["function"], tuple(e["diff"])): e["why"] for e in equivalent}
    killed = [m for m, s in statuses.items() if s in KILLED]
    rest = sorted(m for m in statuses if m not in killed)
    survived, equiv = [], []
    diffs = _diffs(workdir, module, rest)
    for m in rest:
        d = diffs[m]
        key = (function_of(m), tuple(changed_lines(d)))
        if key in known:
            equiv.append((m, known[key]))
        else:
            survived.append((m, statuses[m], d))
    total = len(statuses)
    live = total - len(equiv)
    score = len(killed) / live if live else 1.0
    minutes = (time.perf_counter() - t0) / 60
    print(f"\n{module} against {' '.join(tests)}")
    print(
        f"mutants {total}: killed {len(killed)}, survived {len(survived)}, "
        f"equivalent {len(equiv)}; score {100 * score:.1f}% of non-equivalent "
        f"({minutes:.1f} min)"
    )
    for m, why in equiv:
        print(f"  equivalent {m}: {why}")
    for m, status, d in survived:
        print(f"\n  {status} {m}\n" + "\n".join("    " + line for line in d.splitlines()))
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "module": module,
                    "tests": tests,
                    "total": total,
                    "killed": len(killed),
                    "equivalent": [m for m, _ in equiv],
                    "survived": [{"mutant": m, "status": s, "diff": d} for m, s, d in survived],
                    "score": score,
                },
                indent=1,
            )
            + "\n"
        )
    return 1 if survived else 0


if __name__ == "__main__":
    raise SystemExit(main())
