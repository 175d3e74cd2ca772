"""Fingerprints of the pings a map integrated, so that maps sharing pings are not merged.

A merge is exact only for maps of *disjoint* pings (:mod:`gpumap.merge`): a ping in both maps
would count its clear dark views twice. Each map therefore keeps one 64-bit fingerprint per
integrated ping, the first 8 bytes of a SHA-1 digest of the image (its dtype, shape and bytes,
as the mapper took it) and of the pose (``T_W_S`` as float64): 8 bytes a ping, saved in the map
file as the member ``pings`` (``(n,) uint64``; files of older versions have none, and their
pings are unknown).
Two maps built from the same recording share a ping exactly when the same image came at the
same pose; the chance that two different pings share a fingerprint is about ``n**2 / 2**65``
(1e-10 for 100,000 pings).
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["PingPrints", "ping_print"]


def ping_print(image: np.ndarray, T_W_S: np.ndarray) -> int:
    """The 64-bit fingerprint of one ping: its image (dtype, shape, bytes) and its pose."""
    img = np.ascontiguousarray(image)
    # SHA-1 (hardware-accelerated where the CPU has SHA extensions): 2.5x BLAKE2b's speed here, about
    # 1 ms for a 400 x 512 float32 ping on the loaded 2-core machine, 0.3 ms for uint8; only its first
    # 8 bytes are kept, and nothing here needs resistance to a crafted collision
    h = hashlib.sha1(usedforsecurity=False)
    h.update(f"{img.dtype.str}{img.shape}".encode())
    h.update(memoryview(img).cast("B"))
    h.update(np.ascontiguousarray(T_W_S, dtype="<f8").tobytes())
    return int.from_bytes(h.digest()[:8], "little")


class PingPrints:
    """The fingerprints of a map's pings, in the order they came (a growing uint64 array)."""

    def __init__(self, prints: np.ndarray | None = None) -> None:
        self._a = np.zeros(0, np.uint64) if prints is None else np.asarray(prints, np.uint64).ravel().copy()

    def __len__(self) -> int:
        return len(self._a)

    def array(self) -> np.ndarray:
        """A copy of the fingerprints, ``(n,) uint64``."""
        return self._a.copy()

    def add(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        self.extend(np.array([ping_print(image, T_W_S)], np.uint64))

    def add_batch(self, images: np.ndarray, T_W_S: np.ndarray) -> None:
        self.extend(np.array([ping_print(i, T) for i, T in zip(images, T_W_S, strict=True)], np.uint64))

    def extend(self, prints: np.ndarray) -> None:
        self._a = np.concatenate([self._a, np.asarray(prints, np.uint64).ravel()])

    def clear(self) -> None:
        self._a = np.zeros(0, np.uint64)

    def shared(self, other: np.ndarray) -> int:
        """How many of ``other``'s fingerprints this map holds too."""
        return int(np.isin(np.asarray(other, np.uint64), self._a).sum())


def read_prints(zf, members: dict, headers: dict, n_integrated: int, path) -> PingPrints:
    """The ``pings`` member of an open map file (empty when absent: a file of an older version),
    checked: ``(n,) uint64`` with ``n <= n_integrated``."""
    from gpumap.errors import FormatError

    if "pings.npy" not in members:
        return PingPrints()
    shape, dtype = headers["pings.npy"]
    if len(shape) != 1 or dtype != np.dtype("<u8") or shape[0] > n_integrated:
        raise FormatError(f"Expected 'pings' of shape (n,) uint64 with n <= n_integrated={n_integrated} "
                          f"in {path}, but got {shape} {dtype}")
    with zf.open("pings.npy") as f:
        return PingPrints(np.lib.format.read_array(f, allow_pickle=False))
