"""Capture stamps: a V4L2 buffer time onto the epoch."""

from __future__ import annotations

from capture.sources.opencv import v4l2_buffer_stamp_ns


def test_a_v4l2_buffer_time_is_moved_onto_the_epoch_or_refused() -> None:
    now_ns, mono_ns = 1_700_000_000_000_000_000, 5_000_000_000_000
    # captured 12.5 ms ago on CLOCK_MONOTONIC
    assert v4l2_buffer_stamp_ns((mono_ns - 12_500_000) / 1e6, now_ns, mono_ns) == now_ns - 12_500_000
    assert v4l2_buffer_stamp_ns(0.0, now_ns, mono_ns) is None  # the driver gives none
    assert v4l2_buffer_stamp_ns((mono_ns + 10**8) / 1e6, now_ns, mono_ns) is None  # ahead of now
    assert v4l2_buffer_stamp_ns((mono_ns - 3 * 10**9) / 1e6, now_ns, mono_ns) is None  # another clock
