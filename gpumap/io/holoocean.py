"""HoloOcean-layout sonar datasets (NeuSIS, AONeuS and the methods that reuse their data).

Layout (NeuSIS ``README.md`` and ``load_data.py``, ``github:rpl-cmu/neusis``; the same in
AONeuS ``load_data.py``, ``github:kzhang2/aoneus``, whose repository ships one such dataset,
``data/reduced_baseline_0.6x_sonar``)::

    <dataset>/
    |-- Config.json     # the HoloOcean scenario that recorded it (agents, sensors, settings)
    |-- Data/000.pkl    # one pickle per ping: a dict of the sensors' readings
    |-- Data/001.pkl ...

Conventions, each with where it comes from (HoloOcean's C++ sensors as read in the fork
``github:wellscrosby/MRGHoloOcean``, ``engine/Source/Holodeck/``, BYU FRoStLab's code, MIT):

- **Frame files**: ``Data/*.pkl``, each a dict keyed by sensor name (HoloOcean's state dict;
  a sensor's name is its ``sensor_name`` in the config, else its ``sensor_type``):
  ``"ImagingSonar"`` the polar image, ``"PoseSensor"`` a 4 x 4 pose (AONeuS's sample:
  ``(256, 96) uint8`` and ``(4, 4) float32``, pickled with NumPy 1.x at protocol 4). The
  loaders walk ``os.listdir`` (no order); here frames go in the order of the number in their
  names. Pickles are read with :func:`gpumap.io.safe_pickle.load_pickle` (nothing they name
  is run).
- **Sonar config**: the ``ImagingSonar`` among ``agents[*].sensors`` of ``Config.json``
  (the only one, or the one named by ``sensor=``), its ``configuration``: ``RangeMin``/``RangeMax`` in metres,
  ``Azimuth``/``Elevation`` the full apertures in **degrees** (both loaders apply
  ``math.radians``), ``RangeBins``/``AzimuthBins`` the image size. HoloOcean
  (``ImagingSonar.cpp``, ``ParseSensorParms``) also accepts ``RangeRes``/``AzimuthRes``
  instead of the bin counts (``bins = int(span / res)``); both are read. AONeuS adds
  ``ds_factor`` (a scale its training divides poses and ranges by) and ``simple_denoise``
  (its thresholding): training choices, not geometry; kept in ``meta``, not applied.
- **Image orientation** (HoloOcean ``ImagingSonar.cpp``, ``TickSensorComponent``: the
  result buffer's index is ``rangeIdx * AzimuthBins + azimuthIdx``): rows are range bins,
  columns azimuth bins, C order -- ``(RangeBins, AzimuthBins)``. Row ``i`` holds ranges
  ``[RangeMin + i*res, RangeMin + (i+1)*res)`` with ``res = (RangeMax - RangeMin) / RangeBins``
  (``idx.X = int((r - RangeMin) / RangeRes)``): ascending range, as gpumap's polar image.
  Column ``j`` holds azimuths ``[-Azimuth/2 + j*ares, ...)``, ``ares = Azimuth / AzimuthBins``
  (``idx.Y = int((az - minAzimuth) / AzimuthRes)``, ``minAzimuth = -Azimuth/2`` in
  ``HolodeckSonar.cpp``), so beam ``j`` is centred on ``-Azimuth/2 + (j + 0.5) * ares``: exactly
  :meth:`gpumap.SonarSpec.uniform`. NeuSIS/AONeuS put pixel ``(i, j)`` at the cell's lower edge
  (``r = i*res + r_min``, ``theta = -hfov/2 + j*hfov/W``), half a cell from HoloOcean's binning;
  this reader follows the simulator.
- **Azimuth sign**: ``HolodeckSonar.cpp:inRange`` takes ``az = atan2(-y, x)`` in Unreal's
  left-handed sensor frame (x forward, y right, z up), i.e. positive towards the sensor's
  left: ascending columns are ascending ``theta = atan2(y, x)`` in gpumap's sonar frame
  (x forward, y left, z up; DESIGN.md). No flip. (HoloOcean bins with a fast ``atan2``
  approximation, within about 0.3 deg.)
- **Elevation**: the sensor's polar angle from its up axis within ``90 -+ Elevation/2`` deg:
  a symmetric vertical aperture of ``Elevation`` degrees.
- **Pose** (HoloOcean ``PoseSensor.cpp``): columns 0-2 of the rotation are the sensor's
  forward, left and up axes in HoloOcean's right-handed world (x forward, y left, z up,
  ``docs: usage/units-and-coordinates``), column 3 its position in metres: a ``T_W_P``
  in gpumap's convention. It is the sonar's pose when the ``PoseSensor`` sits on the sonar's
  ``socket`` with the same ``location`` and ``rotation`` (as in AONeuS's shipped config:
  ``SonarSocket``, rotation ``[0, 45, 0]``); the reader checks that in ``Config.json`` and
  refuses a config that mounts them apart unless ``T_P_S`` (the sonar in the pose sensor's
  frame) is given. float32 poses are widened to float64 and checked rigid.
- **Intensity**: uint8 images are scaled by 1/255 (as AONeuS does), uint16 by 1/65535;
  float images (HoloOcean's own output) are clipped to ``[0, 1]`` (its noise can leave it).
  A numeric ``"t"`` entry, when a frame has one, is taken as its time in seconds (AONeuS's
  frames have none; unverified against other datasets).

The same layout is said to be used by SonarSplat and by differentiable space carving, whose
repositories could not be read here: their datasets are read by these rules, unverified.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpumap import limits
from gpumap.errors import check_pose
from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.io.safe_pickle import load_pickle
from gpumap.limits import check_size, declared_product
from gpumap.spec import SonarSpec

__all__ = ["CONFIG_FILE", "DATA_DIR", "HoloOceanSonar", "open_holoocean", "read_holoocean_config"]

CONFIG_FILE = "Config.json"
DATA_DIR = "Data"
MAX_CONFIG_BYTES = 1 << 20
"""1 MiB: the largest ``Config.json`` read (AONeuS's is 3.8 kB)."""

_NUM = re.compile(r"([0-9]+)")


@dataclass(frozen=True)
class HoloOceanSonar:
    """What ``Config.json`` says about the imaging sonar and where its readings are.

    Parameters
    ----------
    spec : SonarSpec or None
        The polar geometry; ``None`` when the config gives neither bin counts nor resolutions
        (then the first image's shape decides, see :func:`open_holoocean`).
    image_key, pose_key : str
        The keys of the image and of the pose in each frame's dict.
    config : dict
        The sonar's ``configuration`` block, and ``ds_factor``/``simple_denoise`` if present.
    span : tuple
        ``(range_min_m, range_max_m, range_res_m or None, azimuth_deg, azimuth_res_deg or None,
        vfov_deg)`` as read, for building ``spec`` from an image's shape.
    """

    spec: SonarSpec | None
    image_key: str
    pose_key: str
    config: dict[str, Any] = field(default_factory=dict)
    span: tuple = ()


def _number(cfg: dict, key: str, where: str, path: str, *, positive: bool = False) -> float | None:
    if key not in cfg:
        return None
    v = cfg[key]
    x = math.nan
    if not isinstance(v, bool) and isinstance(v, (int, float)):
        try:
            x = float(v)
        except OverflowError:  # a JSON integer beyond float range
            pass
    if not math.isfinite(x) or (positive and x <= 0):
        raise FormatError(f"expected {key} in {where} to be a finite {'positive ' if positive else ''}"
                          f"number, but got {v!r}"[:300], path=path)
    return x


def _count(cfg: dict, key: str, where: str, path: str) -> int | None:
    if key not in cfg:
        return None
    v = cfg[key]
    if type(v) is not int or not 2 <= v <= limits.MAX_IMAGE_PIXELS:
        raise FormatError(f"expected {key} in {where} to be an integer >= 2, but got {v!r}"[:300], path=path)
    return v


def _sensors(cfg: object, path: str) -> list[tuple[int, dict]]:
    if not isinstance(cfg, dict) or not isinstance(cfg.get("agents"), list):
        raise FormatError("expected a HoloOcean scenario (a JSON object with a list 'agents'), but "
                          f"got {type(cfg).__name__}" + ("" if not isinstance(cfg, dict) else
                                                         f" with keys {sorted(cfg)[:10]}"), path=path)
    out = []
    for a, agent in enumerate(cfg["agents"]):
        sensors = agent.get("sensors") if isinstance(agent, dict) else None
        if not isinstance(sensors, list):
            raise FormatError(f"expected agents[{a}] to hold a list 'sensors', but it does not", path=path)
        out += [(a, s) for s in sensors if isinstance(s, dict)]
    return out


def _mount(s: dict) -> tuple:
    return (s.get("socket"), s.get("location", [0, 0, 0]), s.get("rotation", [0, 0, 0]))


def read_holoocean_config(path: str | os.PathLike, *, sensor: str | None = None,
                          vfov_deg: float | None = None, check_mount: bool = True) -> HoloOceanSonar:
    """Read a HoloOcean ``Config.json``: the imaging sonar's geometry and its readings' keys.

    Parameters
    ----------
    path : path-like
        The ``Config.json``.
    sensor : str, optional
        The imaging sonar's name when the config has several (default: the only one).
    vfov_deg : float, optional
        Vertical aperture to use instead of the config's ``Elevation``, degrees.
    check_mount : bool
        Refuse a ``PoseSensor`` mounted elsewhere than the sonar (see the module notes).

    Raises
    ------
    FormatError
        Not JSON, not a scenario, no (or an ambiguous) ImagingSonar, a missing or invalid
        range/aperture/bin entry, or a pose sensor mounted apart from the sonar.
    """
    p = os.fspath(path)
    with open(p, "rb") as f:
        check_size(os.fstat(f.fileno()).st_size, MAX_CONFIG_BYTES, "Config.json", path=p)
        raw = f.read(MAX_CONFIG_BYTES + 1)
    check_size(len(raw), MAX_CONFIG_BYTES, "Config.json", path=p)
    try:
        cfg = json.loads(raw.decode("utf-8-sig"))
    except UnicodeDecodeError as e:
        raise FormatError(f"expected UTF-8 JSON, but byte {e.start} is not UTF-8", e.start, p) from None
    except (json.JSONDecodeError, RecursionError) as e:
        raise FormatError(f"expected JSON, but {' '.join(str(e).split())[:200]}", path=p) from None
    found = _sensors(cfg, p)
    sonars = [(a, s) for a, s in found if s.get("sensor_type") == "ImagingSonar"
              and (sensor is None or s.get("sensor_name", "ImagingSonar") == sensor)]
    if not sonars:
        kinds = sorted({str(s.get("sensor_type")) for _a, s in found})
        want = "an ImagingSonar" + ("" if sensor is None else f" named {sensor!r}")
        raise FormatError(f"expected {want} among the agents' sensors, but found {kinds}", path=p)
    if len(sonars) > 1:
        names = [s.get("sensor_name", "ImagingSonar") for _a, s in sonars]
        raise FormatError(f"expected one ImagingSonar, but found {len(sonars)} ({names}): pass "
                          "sensor=NAME", path=p)
    agent, son = sonars[0]
    conf = son.get("configuration", {})
    if not isinstance(conf, dict):
        raise FormatError("expected the ImagingSonar's 'configuration' to be an object, but it is a "
                          f"{type(conf).__name__}", path=p)
    where = "the ImagingSonar configuration"
    vals = {k: _number(conf, k, where, p) for k in ("RangeMin", "RangeMax", "Azimuth", "Elevation")}
    missing = [k for k, v in vals.items() if v is None and not (k == "Elevation" and vfov_deg is not None)]
    if missing:
        raise FormatError(f"expected {', '.join(missing)} in {where} of Config.json, but it has only "
                          f"{sorted(conf)[:20]}", path=p)
    r0, r1, az = vals["RangeMin"], vals["RangeMax"], vals["Azimuth"]
    el = vals["Elevation"] if vfov_deg is None else float(vfov_deg)
    if not 0 <= r0 < r1:
        raise FormatError(f"expected 0 <= RangeMin < RangeMax in {where}, but got {r0} and {r1}", path=p)
    if not 0 < az < 180 or not 0 < el < 180:
        raise FormatError(f"expected apertures in (0, 180) degrees in {where}, but got Azimuth {az} and "
                          f"Elevation {el}", path=p)
    n_bins, n_beams = _count(conf, "RangeBins", where, p), _count(conf, "AzimuthBins", where, p)
    rres = _number(conf, "RangeRes", where, p, positive=True) if n_bins is None else None
    ares = _number(conf, "AzimuthRes", where, p, positive=True) if n_beams is None else None
    spec = None
    if (n_bins or rres) and (n_beams or ares):
        spec = _spec(r0, r1, n_bins, rres, az, n_beams, ares, el, p)
    image_key = son.get("sensor_name", "ImagingSonar")
    poses = [s for a, s in found if a == agent and s.get("sensor_type") == "PoseSensor"]
    pose = next((s for s in poses if _mount(s) == _mount(son)), poses[0] if poses else None)
    if check_mount and pose is not None and _mount(pose) != _mount(son):
        raise FormatError(f"expected the PoseSensor on the sonar's mount (socket, location, rotation "
                          f"{_mount(son)}) so that its pose is the sonar's, but it is at {_mount(pose)}: "
                          "pass T_P_S (the sonar in the pose sensor's frame)"[:400], path=p)
    pose_key = pose.get("sensor_name", "PoseSensor") if pose is not None else "PoseSensor"
    extra = {k: cfg[k] for k in ("ds_factor", "simple_denoise") if k in cfg}
    return HoloOceanSonar(spec, str(image_key), str(pose_key), {**conf, **extra},
                          (r0, r1, rres, az, ares, el))


def _spec(r0: float, r1: float, n_bins: int | None, rres: float | None, az: float, n_beams: int | None,
          ares: float | None, el: float, p: str) -> SonarSpec:
    """HoloOcean's binning: counts split the span; a resolution gives ``int(span / res)`` bins of it."""
    if n_bins is None:
        n_bins = int((r1 - r0) / rres)
        r1 = r0 + n_bins * rres
    if n_beams is None:
        n_beams = int(az / ares)
    step = math.radians(az / n_beams if ares is None else ares)
    for n, what in ((n_bins, "range bins"), (n_beams, "azimuth bins")):
        if n < 2:
            raise FormatError(f"expected at least 2 {what} from Config.json, but its resolution gives {n}",
                              path=p)
    check_size(declared_product(n_bins, n_beams), limits.MAX_IMAGE_PIXELS,
               "the ImagingSonar image (range bins x azimuth bins)", unit="pixels", path=p)
    bearings = -math.radians(az) / 2 + step * (np.arange(n_beams) + 0.5)
    try:
        spec = SonarSpec(r0, r1, n_bins, bearings, math.radians(el))
    except ValueError as e:
        raise FormatError(f"expected a valid sonar geometry in Config.json, but {e}", path=p) from None
    return limits.check_geometry(spec, "the ImagingSonar", path=p)


def _frame_files(data_dir: Path, root: Path) -> list[tuple[int, Path]]:
    by_num: dict[int, Path] = {}
    for f in data_dir.iterdir():
        if f.suffix.lower() != ".pkl":
            continue
        m = _NUM.findall(f.stem)
        if not m or not f.is_file():
            raise FormatError(f"expected numbered frame files ({DATA_DIR}/NNN.pkl, regular files), but "
                              f"found {f.name!r}", path=str(root))
        k = int(m[-1])
        if k in by_num:
            raise FormatError(f"expected one file per frame number, but {by_num[k].name} and {f.name} are "
                              f"both frame {k}", path=str(root))
        by_num[k] = f
    if not by_num:
        raise FormatError(f"expected frame pickles in {DATA_DIR}/ (NNN.pkl), but found none", path=str(root))
    return sorted(by_num.items())


def _image(img: object, key: str, spec_shape: tuple[int, int] | None, name: str) -> np.ndarray:
    if type(img) is not np.ndarray or img.ndim != 2:
        what = f"shape {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
        raise FormatError(f"expected {key!r} to be a 2-D image (range bins x azimuth bins), but it is "
                          f"{what}", path=name)
    if spec_shape is not None and img.shape != spec_shape:
        raise FormatError(f"expected a {key!r} image of {spec_shape} (RangeBins x AzimuthBins from "
                          f"Config.json), but it is {img.shape}", path=name)
    if img.dtype == np.uint8:
        return img.astype(np.float32) / np.float32(255.0)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / np.float32(65535.0)
    if img.dtype == np.bool_:
        return img.astype(np.float32)
    if img.dtype.kind == "f" and img.dtype.itemsize in (2, 4, 8):
        if not np.isfinite(img).all():
            raise FormatError(f"expected finite intensities in {key!r}, but it holds NaN or inf", path=name)
        return np.clip(img, 0.0, 1.0).astype(np.float32)
    raise FormatError(f"expected a uint8, uint16 or float {key!r} image, but it is {img.dtype}", path=name)


def _pose(T: object, key: str, name: str) -> np.ndarray:
    try:
        a = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or type(T) not in (np.ndarray, list, tuple):
        raise FormatError(f"expected {key!r} to be a 4 x 4 pose, but it is a {type(T).__name__}", path=name)
    if a.shape != (4, 4):
        raise FormatError(f"expected {key!r} to be a 4 x 4 pose, but it has shape {a.shape}", path=name)
    try:
        return check_pose(a, key)
    except ValueError as e:
        raise FormatError(str(e), path=name) from None


def _read_frame(f: Path, son: HoloOceanSonar, shape: tuple[int, int] | None,
                T_P_S: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float | None]:
    name = str(f)
    state = load_pickle(f)
    if type(state) is not dict:
        raise FormatError(f"expected a dict of sensor readings (HoloOcean's state), but the pickle holds "
                          f"a {type(state).__name__}", path=name)
    for key in (son.image_key, son.pose_key):
        if key not in state:
            keys = sorted(str(k) for k in state)[:20]
            raise FormatError(f"expected the reading {key!r} (its sensor's name in Config.json), but the "
                              f"frame has only {keys}", path=name)
    img = _image(state[son.image_key], son.image_key, shape, name)
    T = _pose(state[son.pose_key], son.pose_key, name)
    if T_P_S is not None:
        T = T @ T_P_S
    t = state.get("t")
    ts = float(t) if type(t) in (int, float, np.float32, np.float64) and math.isfinite(float(t)) else None
    return img, T, ts


def open_holoocean(
    folder: str | os.PathLike,
    *,
    sensor: str | None = None,
    vfov_deg: float | None = None,
    T_P_S: np.ndarray | None = None,
    stride: int = 1,
    on_bad: Callable[[FormatError], None] | None = None,
) -> Recording:
    """Open a HoloOcean-layout dataset (``Config.json`` + ``Data/NNN.pkl``); see the module notes.

    Parameters
    ----------
    folder : path-like
        The dataset folder.
    sensor : str, optional
        The imaging sonar's ``sensor_name`` when the config has several.
    vfov_deg : float, optional
        Vertical aperture instead of the config's ``Elevation``, degrees.
    T_P_S : (4, 4) float, optional
        The sonar's pose in the pose sensor's frame, for a config that mounts them apart:
        ``T_W_S = T_W_P @ T_P_S``. Default: they share a mount (checked).
    stride : int
        Use every ``stride``-th frame (the others are not read).
    on_bad : callable, optional
        ``on_bad(error)`` for a frame that cannot be read (refused or corrupt pickle, missing
        key, wrong shape, bad pose), which is then skipped; None (default): the error ends the
        iteration.

    Returns
    -------
    Recording
        Kind ``"holoocean"``; frames in the order of their file numbers, each with its
        ``T_W_S``; ``meta`` holds the frame number, the file and the config's extras.

    Raises
    ------
    FormatError
        At open: a bad ``Config.json`` (see :func:`read_holoocean_config`), no frame files, or
        two files of one frame number. When a frame is reached: what is wrong with it.
    """
    root = Path(folder)
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"Expected an integer stride >= 1, but got {stride!r}")
    rel = None
    if T_P_S is not None:
        rel = check_pose(T_P_S, "T_P_S")
    cfg_path = root / CONFIG_FILE
    if not cfg_path.is_file():
        raise FileNotFoundError(f"Expected the sonar's {CONFIG_FILE} in {root}, but it is not there")
    son = read_holoocean_config(cfg_path, sensor=sensor, vfov_deg=vfov_deg, check_mount=rel is None)
    data_dir = root / DATA_DIR
    if not data_dir.is_dir():
        raise FormatError(f"expected the frames in a folder {DATA_DIR}/, but there is none", path=str(root))
    files = _frame_files(data_dir, root)[:: int(stride)]
    spec = son.spec
    if spec is None:  # the config gives no bin counts: the first frame's image decides
        img0 = _read_frame(files[0][1], son, None, rel)[0]
        r0, r1, _rr, az, _ar, el = son.span
        spec = _spec(r0, r1, img0.shape[0], None, az, img0.shape[1], None, el, str(cfg_path))
    shape = spec.image_shape
    extra = {k: son.config[k] for k in ("ds_factor", "simple_denoise") if k in son.config}
    cache: dict[str, list] = {}

    def frames() -> Iterator[SonarFrame]:
        for k, f in files:
            try:
                img, T, ts = _read_frame(f, son, shape, rel)
            except FormatError as e:
                if on_bad is None:
                    raise
                on_bad(e)
                continue
            yield SonarFrame(image=img, spec=spec, timestamp_s=ts, T_W_S=T,
                             meta={"format": "holoocean", "frame": k, "file": str(f), **extra})

    def poses() -> list[np.ndarray | None]:
        if "T" not in cache:  # each pickle holds its image too: read once, then kept
            out: list[np.ndarray | None] = []
            for _k, f in files:
                try:
                    out.append(_read_frame(f, son, shape, rel)[1])
                except FormatError:
                    out.append(None)
            cache["T"] = out
        return [None if T is None else T.copy() for T in cache["T"]]

    return Recording(str(root), "holoocean", frames, has_poses=True, count=lambda: len(files), poses=poses)
