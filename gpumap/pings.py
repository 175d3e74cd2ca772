"""Fingerprints of the pings a map integrated, so that maps sharing pings are not merged.

A merge is exact only for maps of *disjoint* pings (:mod:`gpumap.core.merge`): a ping in both maps
would count its clear dark views twice. Each map therefore keeps one 64-bit fingerprint per
integrated ping, a BLAKE2b digest of the image (its dtype, its shape and :data:`SAMPLE` of its
values, evenly spaced over it, as the mapper took it) and of the pose (``T_W_S`` as float64): 8
bytes a ping, saved in the map file as the member ``pings`` (``(n,) uint64``; files of older
versions have none, and their pings are unknown). Two maps built from the same recording share a
ping when the same image came at the same pose; two different pings share a fingerprint only
when they came at the same pose with the same sampled values (a sonar's speckle makes that
vanishingly rare; a false match refuses a merge, it never merges wrongly), or by chance, about
``n**2 / 2**65`` (1e-10 for 100,000 pings). A sample, not every byte: hashing whole images cost
a GPU mapper 1-2 ms a ping, most of its time at 1 cm (``bench.ab``); the sample costs microseconds.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["SAMPLE", "PingPrints", "ping_print", "ping_prints"]

#: Values of an image that its fingerprint reads, evenly spaced (all of a smaller image).
SAMPLE = 1024


def ping_print(image: np.ndarray, T_W_S: np.ndarray) -> int:
    """The 64-bit fingerprint of one ping: its image (dtype, shape, :data:`SAMPLE` values evenly
    spaced over it) and its pose."""
    img = np.asarray(image)
    flat = img.reshape(-1)
    if flat.size > SAMPLE:
        flat = flat[:: -(-flat.size // SAMPLE)]
    h = hashlib.blake2b(digest_size=8)
    h.update(f"{img.dtype.str}{img.shape}".encode())
    h.update(np.ascontiguousarray(flat).tobytes())
    h.update(np.ascontiguousarray(T_W_S, dtype="<f8").tobytes())
    return int.from_bytes(h.digest(), "little")


def ping_prints(images: np.ndarray, T_W_S: np.ndarray) -> np.ndarray:
    """:func:`ping_print` of every ping of a batch, ``(B,) uint64``, in one pass: the samples of
    all B images in one gather and the poses in one conversion, then each ping's digest from a
    copy of the digest of the shared header (the same bytes ping_print hashes, so the same
    prints). ``images`` (B, ...) array, ``T_W_S`` (B, 4, 4)."""
    imgs = np.asarray(images)
    B = imgs.shape[0]
    if B == 0:
        return np.zeros(0, np.uint64)
    flat = imgs.reshape(B, -1)
    size = flat.shape[1]
    if size > SAMPLE:
        flat = flat[:, :: -(-size // SAMPLE)]
    body = np.ascontiguousarray(flat)
    pose = np.ascontiguousarray(T_W_S, dtype="<f8").reshape(B, -1)
    head = hashlib.blake2b(f"{imgs.dtype.str}{imgs.shape[1:]}".encode(), digest_size=8)
    digests = []
    for b in range(B):
        h = head.copy()
        h.update(body[b])
        h.update(pose[b])
        digests.append(h.digest())
    return np.frombuffer(b"".join(digests), "<u8").astype(np.uint64)  # little-endian, as ping_print


class PingPrints:
    """The fingerprints of a map's pings, in the order they came (a growing uint64 array)."""

    def __init__(self, prints: np.ndarray | None = None) -> None:
        # a buffer that doubles as it fills (a ping appends in O(1), not a copy of every print)
        self._buf = np.zeros(0, np.uint64) if prints is None else np.asarray(prints, np.uint64).ravel().copy()
        self._n = len(self._buf)

    @property
    def _a(self) -> np.ndarray:
        return self._buf[: self._n]

    def __len__(self) -> int:
        return self._n

    def array(self) -> np.ndarray:
        """A copy of the fingerprints, ``(n,) uint64``."""
        return self._a.copy()

    def add(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        self.extend(np.array([ping_print(image, T_W_S)], np.uint64))

    def add_batch(self, images: np.ndarray, T_W_S: np.ndarray) -> None:
        self.extend(ping_prints(images, T_W_S))

    def extend(self, prints: np.ndarray) -> None:
        p = np.asarray(prints, np.uint64).ravel()
        need = self._n + len(p)
        if need > len(self._buf):
            grown = np.zeros(max(need, 2 * len(self._buf), 64), np.uint64)
            grown[: self._n] = self._a
            self._buf = grown
        self._buf[self._n : need] = p
        self._n = need

    def clear(self) -> None:
        self._buf, self._n = np.zeros(0, np.uint64), 0

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
