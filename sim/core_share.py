"""How many cores the other processes leave a training loop, measured while it runs.

Torch's intra-op threads wait for each other at every operation: beside one busy process on 2
cores, a fine-tuning step with 2 threads took 0.74 s (0.22 s alone), with 1 thread 0.39 s
(``python -m posefuse.bench.train_threads``). A loop that asks :class:`CoreShare` every few
steps and sets ``torch.set_num_threads`` to its answer runs on what is free: both cores alone,
one beside a daemon that is busy, both again once it idles.
"""

from __future__ import annotations

import os

import psutil


def usable_cores() -> int:
    """The cores this process may run on (its affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class CoreShare:
    """The cores left by others, from the machine's and this process's CPU time since the
    previous call (the first call measures from construction)."""

    def __init__(self, cores: int | None = None):
        self.cores = cores or usable_cores()
        self._me = psutil.Process()
        psutil.cpu_percent(None)
        self._me.cpu_percent(None)

    def others(self) -> float:
        """Cores the other processes kept busy since the last call (0 .. machine's cores)."""
        total = psutil.cpu_percent(None) / 100.0 * (psutil.cpu_count() or 1)
        own = self._me.cpu_percent(None) / 100.0
        return max(0.0, total - own)

    def free(self) -> int:
        """Threads to run on: the usable cores less those others keep busy (rounded: a core
        busy half the time or more counts), at least 1."""
        return max(1, self.cores - int(self.others() + 0.5))
