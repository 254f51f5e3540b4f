"""A fine-tuning step's wall time alone and beside busy processes, by torch thread count.

python -m posefuse.bench.train_threads [--steps 24] [--busy 1] [--init CKPT]

Fine-tunes from ``--init`` (default: the shipped model's checkpoint) on a tiny training set of
the shipped catalog (2 scenes x 2 views, rendered once into a temporary folder) for
``--steps`` steps, each setting first alone and then with ``--busy`` processes spinning beside
it: 2 threads, 1 thread, and the default (``threads=None``: the cores the others leave,
``sim.core_share``). Prints the median step time of each; a step's time is its optimiser step
(forward, backward, update), the batch's preparation apart (a few ms).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from posefuse.bench.hostile import spin


def step_times(catalog: str, init: str | None, threads: int | None, steps: int, data: str):
    """The wall time of each optimiser step of one short fine-tune."""
    import posefuse.sim.train as train_module

    times: list[float] = []
    original = train_module._Nets.step

    def timed(self, *args, **kwargs):
        t0 = time.perf_counter()
        out = original(self, *args, **kwargs)
        times.append(time.perf_counter() - t0)
        return out

    train_module._Nets.step = timed
    try:
        with tempfile.TemporaryDirectory() as out:
            config = train_module.TrainConfig(
                n_scenes=2,
                views_per_scene=2,
                val_scenes=1,
                minutes=1e6,
                max_iterations=steps,
                warmup=1,
                workers=1,
                threads=threads,
                data_dir=data,
                init=init,
                checkpoint=str(Path(out) / "model.ckpt"),
            )
            train_module.train(catalog, Path(out) / "model.onnx", config)
    finally:
        train_module._Nets.step = original
    return times


def main(argv: list[str] | None = None) -> int:
    from posefuse.service.resources import DEFAULT_CATALOG, DEFAULT_MODEL

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--busy", type=int, default=1, help="spinning processes beside")
    parser.add_argument("--init", default=str(Path(DEFAULT_MODEL).with_suffix(".ckpt")))
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as data:
        for busy in (0, args.busy):
            for threads in (2, 1, None):
                stop = multiprocessing.Event()
                spinners = [multiprocessing.Process(target=spin, args=(stop,)) for _ in range(busy)]
                for p in spinners:
                    p.start()
                try:
                    times = step_times(str(DEFAULT_CATALOG), args.init, threads, args.steps, data)
                finally:
                    stop.set()
                    for p in spinners:
                        p.join()
                label = "adaptive" if threads is None else f"{threads} threads"
                median = float(np.median(times[2:]))  # the first steps warm the kernels
                rows.append((busy, label, median))
                print(f"{busy} busy beside, {label}: median step {median:.2f} s", flush=True)
    print("\n| busy processes beside | torch threads | median step |\n|---|---|---|")
    for busy, label, median in rows:
        print(f"| {busy} | {label} | {median:.2f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
