"""The cores a training loop takes: those the other processes leave, measured between looks."""

import pytest

from posefuse.sim import core_share


class _Me:
    def __init__(self, percent):
        self.percent = percent

    def cpu_percent(self, interval=None):
        return self.percent


@pytest.mark.parametrize(
    "machine_percent, own_percent, free",
    [
        (100.0, 200.0, 2),  # 2 cores all ours: both free to us
        (100.0, 120.0, 1),  # 0.8 of a core someone else's: one left
        (60.0, 100.0, 2),  # 0.2 of a core someone else's: not worth a thread
        (100.0, 0.0, 1),  # both busy with others: still one thread
    ],
)
def test_free_cores_are_the_usable_ones_less_the_others_busy(
    monkeypatch, machine_percent, own_percent, free
):
    monkeypatch.setattr(core_share.psutil, "cpu_count", lambda: 2)
    monkeypatch.setattr(core_share.psutil, "cpu_percent", lambda interval=None: machine_percent)
    share = core_share.CoreShare(cores=2)
    share._me = _Me(own_percent)
    assert share.free() == free


def test_usable_cores_follow_the_affinity():
    assert 1 <= core_share.usable_cores() <= (__import__("os").cpu_count() or 1)
