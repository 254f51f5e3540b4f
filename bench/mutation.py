"""Mutation testing of one estimator module against its own fast tests (mutmut).

    pip install -e ".[dev]"
    nice -n 19 python -m posefuse.bench.mutation geometry            # or estimator/geometry.py
    python -m posefuse.bench.mutation geometry --tests tests/test_geometry.py --max-children 2

mutmut makes many small changes ("mutants") to the module's functions (a ``<`` for a ``<=``,
a constant plus one, an argument dropped, ...) and runs the tests that reach each changed
function: a mutant the tests fail on is *killed*; one they still pass on *survived*, so either
the tests miss a behaviour or the change is *equivalent* (no input can tell it from the
original). The score is killed / (mutants - equivalent).

The run happens in a scratch copy (``--workdir``, default ``$TMPDIR/posefuse-mutation/MODULE``):
the package laid out as ``posefuse/`` beside ``tests/``, and mutmut's own ``mutants/`` copy
inside it, so the checkout, and any process importing it, never sees a mutant. mutmut's results
stay there (``cd WORKDIR && mutmut show NAME`` prints a mutant's diff).

Equivalent mutants are listed in ``bench/mutation_equivalent.json`` by module, each as the
function and the diff's changed lines with a word on why no test can tell them apart, so the
list survives renumbering. The command prints killed, survived (with each diff) and equivalent,
and exits 1 if a survivor is not on the list. It is not part of the README's test command:
a module takes minutes to an hour on 2 cores (docs/testing.md has the measured runs).
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

# each module's own fast tests (seconds, not minutes)
DEFAULT_TESTS = {
    "geometry": ["tests/test_geometry.py"],
    "translation": ["tests/test_translation.py"],
    "association": ["tests/test_association.py"],
    "mixture": ["tests/test_mixture.py"],
    "pose_error": ["tests/test_evaluation.py"],
    "symmetry": ["tests/test_symmetry.py"],
    "verification": ["tests/test_verification.py"],
    "edges": ["tests/test_verification.py"],
    "refinement": ["tests/test_refinement.py"],
}
# what the tests read besides the package: copied next to tests/ as in the checkout
DATA_DIRS = ("catalogs", "models", "recordings")
# a mutant whose tests crash the interpreter (a segfault: e.g. OpenCV given a NaN map) failed
# them as surely as an assertion did
KILLED = ("killed", "timeout", "caught by type check", "segfault")
SKIP_TOP = {"tests", "docs", "build", "dist", "runs", "data", "out", "mutants"}


def module_name(arg: str) -> str:
    """'geometry', 'estimator/geometry.py' or 'posefuse.estimator.core.geometry' -> 'geometry'."""
    name = arg.replace("\\", "/").removesuffix(".py").replace("/", ".")
    name = name.removeprefix("posefuse.").removeprefix("estimator.")
    if not (REPO / "estimator" / f"{name}.py").is_file():
        raise SystemExit(f"no module estimator/{name}.py in {REPO}")
    return name


def _listed_files() -> list[Path]:
    """The checkout's files as git sees them (tracked and untracked, not ignored)."""
    out = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "-z"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.decode()
    return [Path(p) for p in out.split("\0") if p and (REPO / p).is_file()]


def prepare(workdir: Path, name: str, tests: list[str]) -> None:
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
    source = f"posefuse/estimator/{name}.py"
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


def _statuses(workdir: Path, name: str) -> dict[str, str]:
    """{mutant name: status} from mutmut's own record of the run."""
    from mutmut.stats import status_by_exit_code

    meta = workdir / "mutants" / "posefuse" / "estimator" / f"{name}.py.meta"
    data = json.loads(meta.read_text())
    return {k: status_by_exit_code[v] for k, v in data["exit_code_by_key"].items()}


_DIFFS = """
import json, sys
from mutmut.mutation.diff_apply import get_diff_for_mutant
names, path = json.loads(sys.argv[1]), sys.argv[2]
print(json.dumps({n: get_diff_for_mutant(n, path=path) for n in names}))
"""


def _diffs(workdir: Path, name: str, mutants: list[str]) -> dict[str, str]:
    """{mutant: its unified diff}, all in one process (``mutmut show`` starts one per mutant)."""
    if not mutants:
        return {}
    path = f"posefuse/estimator/{name}.py"
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


def load_equivalent(name: str) -> list[dict]:
    if not EQUIVALENT_FILE.is_file():
        return []
    return json.loads(EQUIVALENT_FILE.read_text()).get(name, [])


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
        "module", help="geometry, estimator/geometry.py or posefuse.estimator.core.geometry"
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
    name = module_name(args.module)
    tests = args.tests or DEFAULT_TESTS.get(name)
    if not tests:
        print(f"no default tests for {name}: pass --tests", file=sys.stderr)
        return 2
    workdir = args.workdir or Path(tempfile.gettempdir()) / "posefuse-mutation" / name
    workdir = workdir.resolve()
    t0 = time.perf_counter()
    if args.rerun_survivors:
        if not (workdir / "mutants").is_dir():
            print(f"no earlier run in {workdir}", file=sys.stderr)
            return 2
        last = _statuses(workdir, name)
        again = sorted(m for m, s in last.items() if s not in KILLED)
        for dest in (workdir / "tests", workdir / "mutants" / "tests"):
            shutil.rmtree(dest)
            shutil.copytree(
                REPO / "tests", dest, ignore=shutil.ignore_patterns("node_modules", "__pycache__")
            )
        print(f"re-running {len(again)} mutants of estimator/{name}.py", flush=True)
        if again:
            proc = _mutmut(
                workdir, "run", "--max-children", str(args.max_children), *again, capture=False
            )
            if proc.returncode not in (0, 1):
                print(f"mutmut run exited {proc.returncode}", file=sys.stderr)
                return 2
    elif not args.report_only:
        prepare(workdir, name, tests)
        print(f"mutating estimator/{name}.py against {' '.join(tests)} in {workdir}", flush=True)
        proc = _mutmut(workdir, "run", "--max-children", str(args.max_children), capture=False)
        if proc.returncode not in (0, 1):
            print(f"mutmut run exited {proc.returncode}", file=sys.stderr)
            return 2
    statuses = _statuses(workdir, name)
    equivalent = load_equivalent(name)
    known = {(e["function"], tuple(e["diff"])): e["why"] for e in equivalent}
    killed = [m for m, s in statuses.items() if s in KILLED]
    rest = sorted(m for m in statuses if m not in killed)
    survived, equiv = [], []
    diffs = _diffs(workdir, name, rest)
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
    print(f"\nestimator/{name}.py against {' '.join(tests)}")
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
                    "module": f"estimator/{name}.py",
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
