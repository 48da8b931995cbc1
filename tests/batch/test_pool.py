"""The ordered process pool: results in the items' order whatever order they finish in, a callback per item
as it finishes, and a worker's exception raised in the caller."""

from __future__ import annotations

import math

import pytest

from valve_emulator.batch.pool import run_ordered


@pytest.mark.parametrize("jobs", [1, 2])
def test_results_come_back_in_the_items_order_with_one_callback_each(jobs):
    seen = []
    items = [-3.0, 1.0, -2.0, 4.0]
    assert run_ordered(abs, items, jobs=jobs, done=lambda i, r: seen.append((i, r))) == [3.0, 1.0, 2.0, 4.0]
    assert sorted(seen) == [(0, 3.0), (1, 1.0), (2, 2.0), (3, 4.0)]


def test_an_exception_in_a_worker_is_raised_in_the_caller():
    with pytest.raises(ValueError, match="math domain error"):
        run_ordered(math.sqrt, [4.0, -1.0], jobs=2)


def test_no_items_is_no_results():
    assert run_ordered(abs, [], jobs=2) == []
