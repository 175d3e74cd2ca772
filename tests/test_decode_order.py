"""Pictures decoded ahead by threads come back as a plain loop gives them
(gpumap.io.frame.decoded_in_order)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import needs_data

from gpumap.io.frame import decoded_in_order


def _slow_square(x: int) -> int:
    time.sleep(0.001 * ((x * 7) % 5))  # later items often finish first
    return x * x


@pytest.mark.parametrize("threads", [1, 2, 4])
def test_results_come_in_the_items_order(threads):
    assert list(decoded_in_order(_slow_square, range(40), threads=threads)) == [x * x for x in range(40)]


def test_an_error_is_raised_where_its_item_comes():
    def f(x):
        if x == 5:
            raise ValueError("bad five")
        return x

    got = []
    with pytest.raises(ValueError, match="bad five"):
        for v in decoded_in_order(f, range(20), threads=3):
            got.append(v)
    assert got == [0, 1, 2, 3, 4]


def test_it_reads_at_most_a_window_ahead():
    seen, lock = [], threading.Lock()

    def f(x):
        with lock:
            seen.append(x)
        return x

    it = decoded_in_order(f, range(1000), threads=2, window=4)
    assert next(it) == 0
    time.sleep(0.05)
    assert len(seen) <= 6  # the window, not the whole recording
    it.close()


@needs_data
def test_a_fan_folder_decoded_by_threads_equals_one_thread(monkeypatch):
    from conftest import DATA

    from gpumap.io import open_recording

    monkeypatch.setenv("GPUMAP_DECODERS", "1")
    one = [(f.image, f.T_W_S) for _, f in zip(range(12), open_recording(DATA / "oasis_tank"), strict=False)]
    monkeypatch.setenv("GPUMAP_DECODERS", "3")
    three = [(f.image, f.T_W_S) for _, f in zip(range(12), open_recording(DATA / "oasis_tank"), strict=False)]
    assert len(one) == len(three) == 12
    for (a, Ta), (b, Tb) in zip(one, three, strict=True):
        assert np.array_equal(a, b) and np.array_equal(Ta, Tb)


def test_a_bad_thread_count_is_refused(monkeypatch):
    from gpumap.io.frame import decoder_threads

    monkeypatch.setenv("GPUMAP_DECODERS", "0")
    with pytest.raises(ValueError, match="GPUMAP_DECODERS"):
        decoder_threads()
