"""``solvers.parallel.map_ordered``: results in item order, errors raised at
their item's turn, the same answer for any number of workers."""

import threading
import time

import pytest

from solvers.parallel import default_workers, map_ordered


def test_results_come_in_item_order_whatever_finishes_first():
    def slow_first(i):
        time.sleep(0.05 if i == 0 else 0.0)
        return i * i

    for workers in (1, 2, 3):
        assert list(map_ordered(slow_first, range(7), workers)) == [i * i for i in range(7)]


def test_items_run_on_several_threads_and_at_most_workers_plus_one_ahead():
    names, started = set(), []

    def work(i):
        names.add(threading.current_thread().name)
        started.append(i)
        time.sleep(0.01)
        return i

    it = map_ordered(work, range(20), workers=2)
    assert next(it) == 0
    assert len(started) <= 3  # items are consumed lazily
    assert list(it) == list(range(1, 20))
    assert len(names) == 2


def test_an_error_is_raised_at_its_items_turn():
    def work(i):
        if i == 3:
            raise ValueError("bad item 3")
        return i

    got = []
    with pytest.raises(ValueError, match="bad item 3"):
        for r in map_ordered(work, range(10), workers=2):
            got.append(r)
    assert got == [0, 1, 2]


def test_workers_must_be_positive():
    assert default_workers() >= 1
    with pytest.raises(ValueError, match="workers"):
        list(map_ordered(lambda i: i, range(3), workers=0))
