"""TUM associate.py rules: unique pairs within max_diff, greedy by smallest difference."""

from __future__ import annotations

import numpy as np

from flightkit.datasets.tum import tum_associate

MS = 1_000_000


def brute_force(a: list[int], b: list[int], max_diff: int) -> list[tuple[int, int]]:
    """TUM's associate.py, literally: all candidates, sorted by difference, taken greedily."""
    cands = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) < max_diff)
    used_a: set[int] = set()
    used_b: set[int] = set()
    out = []
    for _d, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out)


def test_each_stamp_used_once_and_closest_wins() -> None:
    a = [0, 10 * MS, 66 * MS, 100 * MS]
    b = [1 * MS, 2 * MS, 65 * MS, 140 * MS]  # 140 ms is 40 ms from 100 ms: too far
    ia, ib = tum_associate(a, b, 20 * MS)
    # 0 takes 1 ms (closest pair overall); 10 ms then gets 2 ms, the next unused one.
    assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == [(0, 0), (1, 1), (2, 2)]


def test_matches_the_reference_algorithm_on_random_stamps() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        a = np.sort(rng.integers(0, 2_000 * MS, 40)).tolist()
        b = rng.integers(0, 2_000 * MS, 55).tolist()  # unsorted on purpose
        ia, ib = tum_associate(a, b, 20 * MS)
        assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == brute_force(a, b, 20 * MS)


def test_offset_and_empty_inputs() -> None:
    ia, ib = tum_associate([100 * MS], [90 * MS], 5 * MS, offset_ns=10 * MS)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    ia, ib = tum_associate([], [1], 5 * MS)
    assert ia.size == 0 and ib.size == 0
