"""bench.profile_frame's timer: each stage's outermost calls counted, nested calls not."""

from posefuse.bench.profile_frame import StageTimer


def test_stage_timer_counts_outermost_calls_only():
    timer = StageTimer()

    def inner(x):
        return x + 1

    wrapped_inner = timer.wrap(inner, "verification")

    def outer(x):
        return wrapped_inner(x) * 2  # a stage function calling another: counted once

    wrapped_outer = timer.wrap(outer, "refinement")
    assert [wrapped_outer(i) for i in range(3)] == [2, 4, 6]
    assert wrapped_inner(5) == 6
    assert dict(timer.calls) == {"refinement": 3, "verification": 1}
    assert set(timer.seconds) == {"refinement", "verification"}
