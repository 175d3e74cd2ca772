"""What the tests of maps mapped apart and merged share: the whole map compared, the tank's frames."""

from __future__ import annotations

import numpy as np
from conftest import DATA


def everything(m) -> dict:
    """A map's values, ping count and for the visible rules their evidence."""
    out = {"values": m.raw_values(), "n": m.n_integrated}
    if m.rule != "plain":
        out.update(m.evidence())
    return out


def assert_same(a, b) -> None:
    """``a`` and ``b`` hold the same map, bit for bit."""
    ea, eb = everything(a), everything(b)
    assert ea.keys() == eb.keys()
    for k in ea:
        np.testing.assert_array_equal(ea[k], eb[k], err_msg=k)


def tank(stride: int):
    """The real tank recording, every ``stride``-th frame."""
    from gpumap.io import open_fan_folder

    return open_fan_folder(DATA / "oasis_tank", stride=stride)
