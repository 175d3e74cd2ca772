"""The public OASIS tank run as its authors ship it: fan PNGs plus ``son_poses.pkl``.

Layout (``github:chaos-whoi/oasis_iros``, ``data/tank/``; read from its loader
``utils/dataset_utils.py:load_data`` and ``reconstruct.py``)::

    data/tank/
    |-- sonar/image_0000.png ... image_1222.png   # Cartesian fans, 398 x 722, RGB but grey
    |-- son_poses.pkl                             # pickle: list of 1,223 poses
    |-- color/, cam_poses.pkl                     # the camera (not read here)

- ``son_poses.pkl`` is a list with one 4 x 4 pose per sonar picture, each a nested list of
  floats (row-major; protocol 4; no NumPy objects). It is read with
  :func:`gpumap.io.safe_pickle.load_pickle`, which refuses anything but containers and
  arrays without running it. A pose is ``X_WS`` in the authors' code (``sonar_voxel_grid.py``
  maps voxel centres into the sonar frame with ``inv(X_WS)``): ``T_W_S`` here, metres.
- Pictures and poses are paired by position: the loader lists ``sonar/*.png`` sorted by
  name and zips that list with the pose list (``son_poses[start:num:step]`` beside
  ``sonar_img_files[start:num:step]``). The reader does the same and refuses a folder whose
  counts differ ("103 poses for 123 pictures") instead of pairing them wrongly.
- The pictures are the same files as the project's converted copy (``shared/data/oasis_tank``
  keeps every 10th; its ``sonar_poses.csv`` equals this pickle to 5e-10), so the fan
  convention and sonar geometry are those of :mod:`gpumap.io.fan` (``FanGeometry()``,
  ``OASIS_SPEC``: 0.1-2.0 m, 398 bins, 130 x 20 deg, 512 beams, from ``configs/base.yaml``).

``open_recording`` picks this reader for a folder holding ``son_poses.pkl`` (and for a clone's
root, through its single ``data/<name>/son_poses.pkl``); a folder that also holds the project's
``sonar_poses.csv`` is read through that table instead (:func:`gpumap.io.fan.open_fan_folder`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from gpumap.errors import check_pose
from gpumap.io.fan import OASIS_SPEC, FanGeometry, _fan_sampler, read_grey_png
from gpumap.io.frame import FormatError, Recording, SonarFrame, frames_skipping_bad
from gpumap.io.safe_pickle import load_pickle
from gpumap.spec import SonarSpec

__all__ = ["POSES_FILE", "open_oasis_folder", "read_oasis_poses"]

POSES_FILE = "son_poses.pkl"
"""The authors' name for the sonar poses' pickle."""


def read_oasis_poses(path: str | os.PathLike) -> np.ndarray:
    """Read the authors' ``son_poses.pkl`` safely and check every pose.

    Parameters
    ----------
    path : path-like
        The pickle: a list (or tuple, or an ``(n, 4, 4)`` array) of 4 x 4 poses, each a nested
        list or an array.

    Returns
    -------
    (n, 4, 4) float64
        ``T_W_S`` of each picture in name order, metres; finite and rigid.

    Raises
    ------
    FormatError
        If the pickle holds anything but containers and arrays (refused without running it),
        is corrupt, is not a sequence of poses, or a pose is not 4 x 4, not finite or not rigid
        (naming the pose).
    """
    p = os.fspath(path)
    obj = load_pickle(p)
    if isinstance(obj, np.ndarray):
        if obj.ndim != 3 or obj.shape[1:] != (4, 4):
            raise FormatError(f"expected an (n, 4, 4) array of poses, but got shape {obj.shape}", path=p)
        items = list(obj)
    elif type(obj) in (list, tuple):
        items = list(obj)
    else:
        raise FormatError(f"expected a list of 4 x 4 poses, but the pickle holds a {type(obj).__name__}",
                          path=p)
    out = np.empty((len(items), 4, 4))
    for i, T in enumerate(items):
        try:
            a = np.asarray(T, dtype=np.float64)
        except (TypeError, ValueError):
            raise FormatError(f"expected pose {i} (of {len(items)}) to be a 4 x 4 grid of numbers, but "
                              f"it is a {type(T).__name__} that is not", path=p) from None
        if a.shape != (4, 4):
            raise FormatError(f"expected pose {i} (of {len(items)}) to be 4 x 4, but it has shape "
                              f"{a.shape}", path=p)
        try:
            out[i] = check_pose(a, f"pose {i} (of {len(items)})")
        except ValueError as e:
            raise FormatError(str(e), path=p) from None
    return out


def _pictures(img_dir: Path) -> list[Path]:
    files = []
    for f in sorted(img_dir.iterdir(), key=lambda f: f.name):  # the authors' order: sorted names
        if f.name.endswith(".png"):
            if not f.is_file():
                raise FormatError(f"expected sonar pictures to be regular files, but {f.name} is not "
                                  "(a folder, pipe or device)", path=str(img_dir))
            files.append(f)
    return files


def open_oasis_folder(
    folder: str | os.PathLike,
    *,
    spec: SonarSpec = OASIS_SPEC,
    geom: FanGeometry | None = None,
    image_dir: str = "sonar",
    stride: int = 1,
    on_bad: Callable[[FormatError], None] | None = None,
) -> Recording:
    """Open the OASIS tank folder as its authors ship it (``sonar/*.png`` + ``son_poses.pkl``).

    Parameters
    ----------
    folder : path-like
        The tank folder (``data/tank`` of a clone).
    spec : SonarSpec
        Polar geometry to sample (default: the OASIS M3000d config, 398 bins x 512 beams).
    geom : FanGeometry, optional
        The pictures' convention (default: OASIS, see :mod:`gpumap.io.fan`).
    image_dir : str
        The pictures' folder inside ``folder``.
    stride : int
        Use every ``stride``-th picture (and its pose).
    on_bad : callable, optional
        ``on_bad(error)`` for a picture that cannot be read (truncated, corrupt, the wrong
        size), which is then skipped; None (default): the error ends the iteration.

    Returns
    -------
    Recording
        Kind ``"oasis"``; every frame carries its ``T_W_S``; ``meta["frame"]`` is the
        picture's position in name order (the pose's index).

    Raises
    ------
    FormatError
        At open: no pictures, the pose pickle refused, corrupt or malformed, or its pose count
        not the picture count. When a picture is reached: a corrupt or wrong-sized picture.
    FileNotFoundError
        If ``son_poses.pkl`` is missing.
    """
    root = Path(folder)
    geom = geom or FanGeometry()
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"Expected an integer stride >= 1, but got {stride!r}")
    img_dir = root / image_dir
    if not img_dir.is_dir():
        raise FormatError(f"expected the sonar pictures in a folder {image_dir}/, but there is none",
                          path=str(root))
    pics = _pictures(img_dir)
    if not pics:
        raise FormatError(f"expected PNG sonar pictures in {img_dir}, but found none", path=str(root))
    pose_path = root / POSES_FILE
    if not pose_path.is_file():
        raise FileNotFoundError(f"Expected the sonar poses {POSES_FILE} beside {image_dir}/ in {root}, "
                                "but it is not there")
    T = read_oasis_poses(pose_path)
    if len(T) != len(pics):
        raise FormatError(f"expected one pose per picture (the authors' loader pairs the i-th picture in "
                          f"name order with the i-th pose), but {POSES_FILE} holds {len(T)} poses for "
                          f"{len(pics)} pictures in {image_dir}/", path=str(root))
    chosen = list(range(0, len(pics), int(stride)))
    sampler = _fan_sampler(spec, geom)
    shape = (geom.n_rows, geom.n_cols)

    def decode(i: int):
        try:
            img = sampler(read_grey_png(pics[i], expected_shape=shape))
        except FormatError as e:
            return e
        np.clip(img, 0.0, 1.0, out=img)
        return SonarFrame(image=img, spec=spec, T_W_S=T[i].copy(),
                          meta={"format": "oasis", "frame": i, "file": str(pics[i])})

    def frames() -> Iterator[SonarFrame]:
        return frames_skipping_bad(decode, chosen, on_bad)  # decoded ahead on a few threads, in order

    return Recording(str(root), "oasis", frames, has_poses=True, count=lambda: len(chosen),
                     poses=lambda: [T[i].copy() for i in chosen])
