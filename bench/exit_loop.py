"""Start and stop posefuse many times beside busy processes: every exit must be clean.

python -m posefuse.bench.exit_loop [--demo 50] [--serve 20] [--busy 1]

- ``--demo N``: ``posefuse demo`` N times in a row; each must exit 0 after printing its score
  line ("... confirmed estimates within ADD-sym ...").
- ``--serve N``: ``posefuse serve --state-dir DIR`` N times; each is sent a few frames of the
  shipped demo recording's cameras, then SIGTERM (as systemd stops it) once they were
  processed; each must exit 0 with its snapshot written and readable (its header line).

``--busy`` processes spin beside all of it (a loaded cell PC). Prints a line per run and the
exit codes counted; a non-zero count is printed with the run's last output lines.
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from posefuse.bench.hostile import Served, spin
from posefuse.bench.service_latency import peer_config


def run_demo() -> tuple[int, str]:
    proc = subprocess.run(
        [sys.executable, "-m", "posefuse.cli", "demo"], capture_output=True, text=True
    )
    out = proc.stdout + proc.stderr
    ok = proc.returncode == 0 and "confirmed estimates within ADD-sym" in out
    return (proc.returncode if not ok or proc.returncode else 0), out


def run_serve(state_dir: Path) -> tuple[int, str]:
    """One serve: start, a few frames, SIGTERM; (exit code, or -1000 for no snapshot; output)."""
    import zenoh

    from posefuse.service.recording import read_messages
    from posefuse.service.resources import DEFAULT_RECORDING
    from posefuse.service.settings import put_camera_message

    try:
        daemon = Served("--state-dir", str(state_dir), cell="posefuse")
    except RuntimeError as exc:
        return -1001, str(exc)
    try:
        sent = 0
        with zenoh.open(peer_config(daemon.zport)) as session:
            time.sleep(0.5)
            for m in read_messages(DEFAULT_RECORDING):
                if "/cam/" not in m.key:
                    continue
                put_camera_message(session, m.key, m.payload)
                sent += m.key.endswith("/image")
                if sent >= 4:
                    break
            t0 = time.monotonic()
            while time.monotonic() - t0 < 60 and daemon.stats()["frames_handled"] < sent:
                time.sleep(0.2)
        daemon.stop()  # SIGTERM, with the frames in flight
        code, out = daemon.proc.returncode, daemon.output()
    finally:
        daemon.close()
    try:
        with open(state_dir / "estimator.state", "rb") as f:
            json.loads(f.readline())
    except (OSError, ValueError):
        return (code or -1000), out
    return code, out


def _repeat(what: str, n: int, run, codes: collections.Counter) -> None:
    """``run()`` n times, each exit code counted; a failed run's last output lines printed."""
    for k in range(n):
        t0 = time.monotonic()
        code, out = run()
        codes[code] += 1
        print(f"{what} {k + 1}/{n}: exit {code} in {time.monotonic() - t0:.0f} s", flush=True)
        if code:
            print("\n".join(out.splitlines()[-15:]), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", type=int, default=50, help="demo runs")
    parser.add_argument("--serve", type=int, default=20, help="serve start-stops")
    parser.add_argument("--busy", type=int, default=1, help="processes spinning beside")
    args = parser.parse_args(argv)
    stop = multiprocessing.Event()
    spinners = [multiprocessing.Process(target=spin, args=(stop,)) for _ in range(args.busy)]
    for p in spinners:
        p.start()
    codes: dict[str, collections.Counter] = {
        "demo": collections.Counter(),
        "serve": collections.Counter(),
    }
    try:
        _repeat("demo", args.demo, run_demo, codes["demo"])
        with tempfile.TemporaryDirectory() as state:
            _repeat("serve", args.serve, lambda: run_serve(Path(state)), codes["serve"])
    finally:
        stop.set()
        for p in spinners:
            p.join()
    for what, counted in codes.items():
        if sum(counted.values()):
            print(
                f"{what}: exit codes {dict(sorted(counted.items()))} "
                f"of {sum(counted.values())} runs"
            )
    return 0 if all(set(c) <= {0} for c in codes.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
