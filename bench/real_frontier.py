"""``python -m bench real_frontier``: every rule, the surface layer and the public OASIS reconstruction
on one judge: the real tank's held-out first returns, phantoms in front against misses.

The full real run (1,223 frames): frames 0-799 mapped at the sonar's rate (every frame), 5 cm
(:func:`gpumap.spec.auto_grid`), threshold 0.4; held-out frames 800-1222 judged by
:func:`gpumap.layers.first_return.first_return_score` (per beam with a return: the map's nearest occupied
voxel in its fan agrees within 2 voxels, lies in front (a phantom), or is farther / absent (missing)).
Every map is judged twice: whole, and inside the public code's configured box only (configs/base.yaml:
2.4 x 2.4 x 1.3 m from (-0.5, -1.2, -0.5); outside it every map is made unknown), the comparison
issue 36 reports.

Rows, each judged alike:

- every rule of :data:`gpumap.geometry.RULES`, read at its defaults (the row of the rule that
  ``MinMaxMapper(rule=None)`` picks is marked the default), then the frontier rows of
  :data:`FRONTIERS` (one line each: the evidence rule at other ``bright_share`` values, and its
  calibrated decision at other ``miss_cost`` values where the mapper has it). Any
  row may carry options (``--row RULE:NAME=VALUE,...``): those that are read-time properties of
  :class:`gpumap.MinMaxMapper` (``bright_share``, ``share_z``, ``carve_views``, ...) are set on the
  one map of that rule before it is read, the others are passed to its constructor (a map of its
  own);
- the surface layer (:func:`gpumap.layers.surface_live.surface_from_mapper` on the evidence map of frames
0-799,
  as ``bench.surface`` builds it);
- the public OASIS reconstruction (chaos-whoi/oasis_iros), its ``update_voxel_grid`` unmodified, run
  by ``bench.oasis_public`` in its own environment (``--oasis-python``: an interpreter with open3d and
  opencv) on the same frames' fan PNGs and poses; its reconstruction is the authors' (a voxel is in
  their ``voxel_grid`` when more than 50 % of the views that reached it detected it, per-range
  adaptive detection). Their box is set to ours (their config takes ``voxel_grid_origin`` /
  ``voxel_grid_size``) but their voxel is tied to the fan's pixel (2.0 / 398 m x their downsample
  10 = 5.025 cm), so their grid is resampled onto ours: each of our voxels takes the state
  (occupied / observed / unknown) of their voxel holding its centre (:func:`resample_to_grid`;
  same origin, so the two differ by at most 0.5 % of the distance from it). It is also judged
  on its own grid without resampling (``native``). ``every`` feeds every frame; ``reconstruct``
  feeds them as their ``reconstruct.py`` does (a frame whose position moved less than 1 cm since
  the last one fed is skipped); ``config-box`` every frame in their configs/base.yaml box;
  ``as-published`` as their ``reconstruct.py`` runs with their config (the skip and their box).

Writes ``bench/results/real_frontier.json`` and ``real_frontier.png``::

    python -m bench real_frontier --oasis-git /path/to/oasis_iros.git --oasis-python /path/to/venv/bin/python
    python -m bench real_frontier --no-oasis --judge-stride 5       # quicker, without the public code
    python -m bench real_frontier --report BENCHMARKS.md
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import json
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import TMP, Section, bench_parser, load_average, oasis_full_dir, run_header, write_json

SCHEMA = "gpumap-real-frontier/1"
MAPPED, HELD = (0, 800), (800, 1223)
#: Frontiers: (rule, read-time options held fixed, the read-time option varied, its values), read on the
#: rule's one map beside its default; one whose rule is not in RULES, or whose options the mapper does not
#: have, is left out, and a value the mapper refuses skips its row.
FRONTIERS: tuple[tuple[str, dict[str, Any], str, tuple[Any, ...]], ...] = (
    ("evidence", {}, "bright_share", (0.1, 0.35, 0.5, 0.65, 0.8)),
    ("evidence", {"decision": "calibrated"}, "miss_cost", (1.0, 10.0, 100.0, 1e4, 1e5)),
)
#: OASIS runs: name -> (min_pose_delta m, box: "ours" or "config").
OASIS_VARIANTS = {"every": (0.0, "ours"), "reconstruct": (0.01, "ours"), "config-box": (0.0, "config"),
                  "as-published": (0.01, "config")}
OASIS_RES_M = 2.0 / 398  # the fan's pixel: their voxel is this x their downsample factor
BATCH = 32


@dataclass(frozen=True)
class Row:
    """One map on the judge: a rule (None: the mapper's default) with options (module docstring)."""

    rule: str | None
    options: Mapping[str, Any] = field(default_factory=dict)
    label: str = ""

    @property
    def name(self) -> str:
        if self.label:
            return self.label
        opts = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                         for k, v in self.options.items())
        return f"{self.rule or 'default'}" + (f" ({opts})" if opts else "")


def parse_row(text: str) -> Row:
    """``RULE`` or ``RULE:NAME=VALUE,NAME=VALUE`` (values as Python literals) -> a :class:`Row`."""
    rule, _, rest = text.partition(":")
    opts: dict[str, Any] = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq or not k.strip():
            raise ValueError(f"Expected RULE:NAME=VALUE[,NAME=VALUE...] for --row, but got {text!r}")
        try:
            opts[k.strip()] = ast.literal_eval(v.strip())
        except (ValueError, SyntaxError):
            opts[k.strip()] = v.strip()
    return Row(rule.strip() or None, opts)


def read_time_options() -> set[str]:
    """Options a mapper takes after it was built: the settable properties of MinMaxMapper."""
    import gpumap

    return {k for k, v in inspect.getmembers(gpumap.MinMaxMapper) if isinstance(v, property) and v.fset}


def split_options(options: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``options`` -> (constructor options, read-time options); unknown names raise ``ValueError``."""

    import dataclasses

    from gpumap.core.params import MapperParams

    read, build = read_time_options(), {f.name for f in dataclasses.fields(MapperParams)}
    bad = sorted(set(options) - read - build)
    if bad:
        raise ValueError(f"Expected row options among MinMaxMapper's read-time properties {sorted(read)} or "
                         f"its parameters, but got {bad}")
    return ({k: v for k, v in options.items() if k not in read},
            {k: v for k, v in options.items() if k in read})


def default_rows() -> list[Row]:
    """Every rule of RULES at its defaults, then each rule's frontier (:data:`FRONTIERS`)."""
    from gpumap.geometry import RULES

    rows, read = [Row(r) for r in RULES], read_time_options()
    for rule, fixed, option, values in FRONTIERS:
        if rule in RULES and {*fixed, option} <= read:
            rows += [Row(rule, {**fixed, option: x}) for x in values]
    return rows


# ------------------------------------------------------------------------------ OASIS on our grid
def resample_to_grid(occupied: np.ndarray, observed: np.ndarray, origin_m: Sequence[float], voxel_m: float,
                     grid) -> np.ndarray:
    """Another grid's map on ``grid``: each voxel of ``grid`` takes the state of the source voxel that
    holds its centre.

    Parameters
    ----------
    occupied, observed : (sx, sy, sz) bool
        The source grid's occupied and observed voxels (occupied implies observed).
    origin_m : (3,) float
        The source grid's minimum corner, metres; its voxel ``(i, j, k)`` spans
        ``origin + [idx, idx + 1) * voxel_m``.
    voxel_m : float
        The source grid's voxel edge, metres.
    grid : gpumap.GridSpec

    Returns
    -------
    (nx, ny, nz) float32 over ``grid``: 1 occupied, 0 observed and not occupied, NaN unknown (never
    observed, or its centre outside the source grid).
    """
    occ, obs = np.asarray(occupied, bool), np.asarray(observed, bool)
    if occ.shape != obs.shape or occ.ndim != 3:
        raise ValueError(f"Expected occupied and observed of one 3-D shape, but got {occ.shape} and "
                         f"{obs.shape}")
    if np.any(occ & ~obs):
        raise ValueError("Expected every occupied voxel to be observed, but some are not")
    if not voxel_m > 0:
        raise ValueError(f"Expected voxel_m > 0, but got {voxel_m}")
    lo, s = np.asarray(grid.min_corner_m, float), float(grid.voxel_size_m)
    axes = [np.floor((lo[a] + (np.arange(n) + 0.5) * s - float(origin_m[a])) / voxel_m).astype(np.int64)
            for a, n in enumerate(grid.shape)]
    inside = [(ix >= 0) & (ix < occ.shape[a]) for a, ix in enumerate(axes)]
    out = np.full(grid.shape, np.nan, np.float32)
    sel = np.ix_(*inside)
    src = np.ix_(*(ix[m] for ix, m in zip(axes, inside, strict=True)))
    out[sel] = np.where(occ[src], 1.0, np.where(obs[src], 0.0, np.nan))
    return out


def _oasis_source(a) -> tuple[Path, str | None]:
    """A checkout of the public code: ``--oasis-src`` as it is, or ``--oasis-git``'s HEAD exported to
    TMP (kept); with the commit where known."""
    if a.oasis_src:
        try:
            commit = subprocess.run(["git", "-C", str(a.oasis_src), "rev-parse", "HEAD"], capture_output=True,
                                    text=True, check=True).stdout.strip()
        except (subprocess.CalledProcessError, OSError):
            commit = None
        return Path(a.oasis_src), commit
    git = ["git", f"--git-dir={a.oasis_git}"]
    commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True,
                            check=True).stdout.strip()
    dest = TMP / f"oasis_iros_{commit[:12]}"
    if not (dest / "sonar_reconstruction" / "sonar_voxel_grid.py").is_file():
        dest.mkdir(parents=True, exist_ok=True)
        tar = subprocess.run([*git, "archive", "HEAD", "sonar_reconstruction", "utils", "configs"],
                             capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    return dest, commit


def run_oasis(a, variant: str, src: Path, commit: str | None, pngs: list[str], poses: np.ndarray,
              grid) -> dict[str, Any]:
    """The public code on frames MAPPED in its own interpreter (cached in TMP by its inputs): its grid."""
    from .oasis_public import BASE_BOX

    delta, box = OASIS_VARIANTS[variant]
    if box == "ours":
        origin = np.asarray(grid.min_corner_m, float)
        size = np.asarray(grid.shape, float) * grid.voxel_size_m
    else:
        origin, size = np.asarray(BASE_BOX[0], float), np.asarray(BASE_BOX[1], float)
    frames = range(*MAPPED)
    job = {"pngs": np.array([pngs[k] for k in frames]), "poses": poses[list(frames)],
           "downsample": np.int64(a.oasis_downsample), "grid_origin": origin, "grid_size": size,
           "min_pose_delta": np.float64(delta)}
    key = hashlib.sha256(json.dumps({
        "commit": commit, "src": str(src), "pngs": [Path(p).name for p in job["pngs"]],
        "poses": np.round(job["poses"], 9).tolist(), "ds": a.oasis_downsample, "origin": origin.tolist(),
        "size": size.tolist(), "delta": delta}).encode()).hexdigest()[:16]
    out = TMP / f"oasis_grid_{variant}_{key}.npz"
    if a.oasis_rerun or not out.is_file():
        TMP.mkdir(parents=True, exist_ok=True)
        job_path = TMP / f"oasis_job_{key}.npz"
        np.savez(job_path, **job)
        # by path: the runner imports nothing of gpumap or bench, so it runs in the public code's interpreter
        cmd = [a.oasis_python, str(Path(__file__).with_name("oasis_public.py")), "--oasis-src", str(src),
               "--job", str(job_path), "--out", str(out)]
        print("running", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
    with np.load(out) as z:
        g = {k: z[k] for k in z.files}
    shape = tuple(int(x) for x in g["shape"])
    occ = np.zeros(shape, bool)
    occ[tuple(g["occupied"].T)] = True
    obs = g["obs_count"] > 0
    ratio_occ = g["occ_ratio"] > float(g["occ_ratio_thresh"])
    return {"variant": variant, "min_pose_delta_m": delta, "box": box, "downsample": a.oasis_downsample,
            "voxel_m": float(g["voxel_size"]), "origin_m": g["origin"].tolist(), "shape": list(shape),
            "frames_fed": len(g["fed"]), "frames_offered": len(frames), "seconds": float(g["seconds"]),
            "ms_per_frame_median": float(np.median(g["ms_per_frame"])), "versions": str(g["versions"]),
            "occupied_native": int(occ.sum()), "observed_native": int(obs.sum()),
            # their voxel_grid against their own occ_ratio > 0.5 (reconstruct.py's occupancy_grid): voxels
            # where the two definitions differ
            "voxel_grid_vs_occ_ratio_diff": int((occ != ratio_occ).sum()),
            "cache": str(out), "_occ": occ, "_obs": obs}


# ------------------------------------------------------------------------------ the run
def _load(path: Path, progress: bool):
    """The recording's spec, (n, bins, beams) float32 images, (n, 4, 4) poses and each frame's fan PNG."""
    from gpumap.io import open_recording

    rec = open_recording(path)
    n = rec.count()
    images, poses, pngs, spec = None, np.empty((n, 4, 4)), [], None
    for i, f in enumerate(common.progress_bar(iter(rec), total=n, desc="read", disable=not progress)):
        if images is None:
            spec, images = f.spec, np.empty((n, *f.image.shape), np.float32)
        images[i], poses[i] = f.image, f.T_W_S
        pngs.append(str(f.meta.get("file", "")))
    return spec, images, poses, pngs


def public_box(downsample: int) -> tuple[np.ndarray, np.ndarray]:
    """The public code's configured box as its grid covers it: (min, max) corners, metres (its shape is
    ``int(size / voxel + 1)`` voxels per axis from ``voxel_grid_origin``)."""
    from .oasis_public import BASE_BOX

    lo, size, vs = np.asarray(BASE_BOX[0], float), np.asarray(BASE_BOX[1], float), downsample * OASIS_RES_M
    return lo, lo + (size / vs + 1).astype(int) * vs


def centres_in_box(grid, lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels of ``grid`` whose centres lie in the box ``[lo, hi)`` (metres)."""
    c = [grid.min_corner_m[a] + (np.arange(n) + 0.5) * grid.voxel_size_m for a, n in enumerate(grid.shape)]
    m = [(x >= lo[a]) & (x < hi[a]) for a, x in enumerate(c)]
    return m[0][:, None, None] & m[1][None, :, None] & m[2][None, None, :]


def _judge(values: np.ndarray, grid, thr: float, images, poses, frames: range, spec) -> dict[str, Any]:
    from gpumap.layers.first_return import first_return_score

    t0 = time.perf_counter()
    s = first_return_score(values, grid, thr, ((images[i], poses[i]) for i in frames), spec)
    return {**s.to_dict(), "seconds": time.perf_counter() - t0}


def _say(name: str, r: dict) -> None:
    j, b = r["judge"], r["judge_box"]
    print(f"{name:32s} occupied {r['occupied']:7,d}: agree {j['agreement']:.1%}, "
          f"phantom {j['phantom_rate']:.1%}, missing {j['missing_rate']:.1%} ({j['seconds']:.0f} s); in the "
          f"public box {b['agreement']:.1%} / {b['phantom_rate']:.1%} / {b['missing_rate']:.1%}", flush=True)


def _parser():
    ap = bench_parser("real_frontier", __doc__, out="bench/results", voxel=0.05, backend="auto",
                      progress=True, report="real_frontier.json")
    ap.add_argument("--data", type=Path, default=None,
                    help="the full run's recording folder (default: found)")
    ap.add_argument("--threshold", type=float, default=0.4, help="bright / occupied (default 0.4)")
    ap.add_argument("--judge-stride", type=int, default=1, help="judge every N-th held-out frame (default 1)")
    ap.add_argument("--row", action="append", default=[], metavar="RULE[:NAME=VALUE,...]",
                    help="another row: a rule with options (read-time ones set on its map), repeatable")
    ap.add_argument("--no-default-rows", action="store_true", help="only the --row rows (and surface, OASIS)")
    ap.add_argument("--no-surface", action="store_true", help="without the surface layer")
    ap.add_argument("--no-oasis", action="store_true", help="without the public OASIS code")
    ap.add_argument("--oasis-src", type=Path, default=None, help="a checkout of chaos-whoi/oasis_iros")
    ap.add_argument("--oasis-git", type=Path, default=None,
                    help="or its git directory (a bare mirror): HEAD is exported to bench/results/tmp")
    ap.add_argument("--oasis-python", default=sys.executable,
                    help="the interpreter of the public code's environment (open3d, opencv; default "
                    "this one)")
    ap.add_argument("--oasis-variants", nargs="+", default=["every", "reconstruct", "as-published"],
                    choices=list(OASIS_VARIANTS),
                    help="every: every frame; reconstruct: its reconstruct.py's 1 cm frame skip; config-box: "
                    "every frame in its configs/base.yaml box; as-published: both, as its reconstruct.py "
                    "runs (default every reconstruct as-published)")
    ap.add_argument("--oasis-downsample", type=int, default=10,
                    help="its image downsample factor: voxel = factor x 2 m / 398 (default 10: 5.025 cm)")
    ap.add_argument("--oasis-rerun", action="store_true",
                    help="run the public code even where its grid is cached")
    return ap


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if SECTION.reported(a):
        return 0
    if a.judge_stride < 1:
        raise SystemExit(f"bench.real_frontier: expected --judge-stride >= 1, but got {a.judge_stride}")
    if not a.no_oasis and (a.oasis_src is None) == (a.oasis_git is None):
        raise SystemExit("bench.real_frontier: expected one of --oasis-src or --oasis-git (or --no-oasis)")
    rows = [] if a.no_default_rows else default_rows()
    rows += [parse_row(t) for t in a.row]
    for r in rows:
        split_options(r.options)  # refuse an unknown option before the long part
    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.real_frontier: the full tank run was not found; get it as "
                         "shared/data/README.md says (oasis_tank_full/get_images.sh) and pass --data")
    import gpumap
    from gpumap.spec import auto_grid

    t_start = time.perf_counter()
    spec, images, poses, pngs = _load(Path(data), not a.no_progress)
    if len(images) < HELD[1]:
        raise SystemExit(f"bench.real_frontier: expected the full run of {HELD[1]} frames, but {data} holds "
                         f"{len(images)}")
    grid, thr = auto_grid(spec, poses, a.voxel), a.threshold
    held, mapped = range(HELD[0], HELD[1], a.judge_stride), np.arange(*MAPPED)
    default_rule = gpumap.MinMaxMapper(spec, grid, "numpy", MapperParams(threshold=thr)).rule
    box_lo, box_hi = public_box(a.oasis_downsample)
    in_box = centres_in_box(grid, box_lo, box_hi)

    def judged(v: np.ndarray) -> dict[str, Any]:
        """Both judges: the whole map, and the map inside the public code's configured box only."""
        return {"judge": _judge(v, grid, thr, images, poses, held, spec),
                "judge_box": _judge(np.where(in_box, v, np.nan), grid, thr, images, poses, held, spec)}

    res: dict[str, Any] = {
        **run_header(SCHEMA, argv), "data": str(data), "voxel_size_m": a.voxel, "threshold": thr,
        "grid": grid.to_dict(), "grid_shape": list(grid.shape), "mapped_frames": list(MAPPED),
        "held_out_frames": list(HELD), "judge_stride": a.judge_stride, "judged_frames": len(held),
        "default_rule": default_rule, "public_box_m": [box_lo.tolist(), box_hi.tolist()],
        "public_box_voxels": int(in_box.sum()), "rows": []}
    mappers: dict[tuple, Any] = {}

    def mapper(rule: str | None, build: dict[str, Any]):
        key = (rule or default_rule, tuple(sorted(build.items())))
        if key not in mappers:
            m = gpumap.MinMaxMapper(spec, grid, a.backend, MapperParams(rule=rule, threshold=thr, **build))
            t0 = time.perf_counter()
            for i in range(0, len(mapped), BATCH):
                b = mapped[i:i + BATCH]
                m.integrate_batch(images[b], poses[b])
            m.synchronize()
            mappers[key] = (m, time.perf_counter() - t0)
            res["backend"] = m.backend
        return mappers[key]

    for row in rows:
        build, read = split_options(row.options)
        m, secs = mapper(row.rule, build)
        before = {k: getattr(m, k) for k in read}
        try:
            for k, v in read.items():
                setattr(m, k, v)
            v = m.values()
        except ValueError as e:  # a value this mapper refuses (a frontier of another version): said, skipped
            print(f"{row.name}: skipped ({e})", flush=True)
            continue
        finally:
            for k, old in before.items():
                setattr(m, k, old)
        r = {"name": row.name, "kind": "rule", "rule": m.rule, "options": dict(row.options),
             "default": m.rule == default_rule and not row.options, "map_seconds": secs,
             "observed": int(np.isfinite(v).sum()), "occupied": int((v >= thr).sum()), **judged(v)}
        res["rows"].append(r)
        _say(r["name"], r)
    if not a.no_surface:
        from gpumap.layers.surface_live import surface_from_mapper

        m, _ = mapper("evidence", {})
        t0 = time.perf_counter()
        layer = surface_from_mapper(m, images[mapped], poses[mapped])
        v = layer.values()
        r = {"name": "surface layer", "kind": "surface", "rule": "evidence", "options": {}, "default": False,
             "map_seconds": time.perf_counter() - t0, "observed": int(np.isfinite(v).sum()),
             "occupied": int((v >= thr).sum()), "candidates": layer.stats["candidates"], **judged(v)}
        res["rows"].append(r)
        _say(r["name"], r)
    mappers.clear()  # free the maps before the public code runs
    if not a.no_oasis:
        src, commit = _oasis_source(a)
        res["oasis"] = {"src": str(src), "commit": commit, "python": a.oasis_python, "runs": []}
        for variant in a.oasis_variants:
            o = run_oasis(a, variant, src, commit, pngs, poses, grid)
            occ, obs = o.pop("_occ"), o.pop("_obs")
            v = resample_to_grid(occ, obs, o["origin_m"], o["voxel_m"], grid)
            r = {"name": f"OASIS ({variant})", "kind": "oasis", "rule": None, "options": {"variant": variant},
                 "default": False, "map_seconds": o["seconds"], "observed": int(np.isfinite(v).sum()),
                 "occupied": int((v >= thr).sum()), **judged(v)}
            lo = np.asarray(o["origin_m"])
            hi = lo + np.asarray(o["shape"]) * o["voxel_m"]
            native = gpumap.GridSpec(tuple(lo), tuple(hi), o["voxel_m"])
            nv = np.where(occ, 1.0, np.where(obs, 0.0, np.nan)).astype(np.float32)
            o["judge_native"] = _judge(nv, native, thr, images, poses, held, spec)
            res["oasis"]["runs"].append(o)
            res["rows"].append(r)
            _say(r["name"], r)
            j = o["judge_native"]
            print(f"{'  ... on its own grid':32s} occupied {o['occupied_native']:7,d}: "
                  f"agree {j['agreement']:.1%}, phantom {j['phantom_rate']:.1%}, "
                  f"missing {j['missing_rate']:.1%}", flush=True)
    res["seconds_total"], res["load_end"] = time.perf_counter() - t_start, load_average()
    path = write_json(a.out / "real_frontier.json", res, digits=4)
    picture(res, a.out / "real_frontier.png")
    print(f"wrote {path} and real_frontier.png ({res['seconds_total']:.0f} s); BENCHMARKS.md: "
          f"python -m bench real_frontier --report BENCHMARKS.md")
    return 0


# ------------------------------------------------------------------------------ the documents
def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``real_frontier.json``."""
    m = res["machine"]
    o = res.get("oasis") or {}
    runs = {r["variant"]: r for r in o.get("runs", [])}
    lo, hi = res["public_box_m"]
    box = " x ".join(f"{h - q:.2f}" for q, h in zip(lo, hi, strict=True)) + " m from (" + ", ".join(
        f"{q:g}" for q in lo) + ")"
    opts = sorted({(r["rule"], k) for r in res["rows"] if r["kind"] == "rule" for k in r["options"]})
    options = ", ".join(f"{rule} `{k}`" for rule, k in opts) or "none"
    out = [common.template("real-frontier", res=res, m=m, load=m.get("load_avg_start"),
                           load_end=res.get("load_end"), commit=(o.get("commit") or "unknown")[:12], box=box,
                           options=options)]
    for r in res["rows"]:
        j = r["judge"]
        name = f"**{r['name']}** (default)" if r.get("default") else r["name"]
        b = r["judge_box"]
        out.append(f"| {name} | {r['occupied']:,} | {100 * j['agreement']:.1f} % | "
                   f"{100 * j['phantom_rate']:.1f} % | {100 * j['missing_rate']:.1f} % | "
                   f"{100 * b['agreement']:.1f} / {100 * b['phantom_rate']:.1f} / "
                   f"{100 * b['missing_rate']:.1f} % |")
    if runs:
        out += ["", common.template("real-frontier-oasis")]
        for name, x in runs.items():
            j = x["judge_native"]
            out.append(f"| {name} | {x['frames_fed']} of {x['frames_offered']} | "
                       f"{x['voxel_m'] * 100:.3f} cm, {' x '.join(map(str, x['shape']))} | "
                       f"{x['occupied_native']:,} | {100 * j['agreement']:.1f} / "
                       f"{100 * j['phantom_rate']:.1f} / {100 * j['missing_rate']:.1f} % | "
                       f"{x['voxel_grid_vs_occ_ratio_diff']} | {x['ms_per_frame_median']:.0f} |")
    out += ["", f"![phantoms against misses]({folder.as_posix()}/real_frontier.png)"]
    return "\n".join(out)


SECTION = Section("real-frontier", "## Every rule against the public OASIS reconstruction on real held-out "
                  "frames (issue #36)", "real_frontier.json", markdown)


def _short(r: dict) -> str:
    """A plot label: the rule, or only its option values where it has options (the legend names them)."""
    if r["kind"] != "rule" or not r["options"]:
        return r["name"] + (" (default)" if r.get("default") else "")
    return " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in r["options"].values())


def _joined(names: list[str]) -> str:
    """One label for the rows on one point: ``calibrated 10, 100`` for ``calibrated 10`` and 100."""
    heads = {n.rpartition(" ")[0] for n in names}
    if len(names) > 1 and len(heads) == 1 and next(iter(heads)):
        return f"{next(iter(heads))} " + ", ".join(n.rpartition(" ")[2] for n in names)
    return ", ".join(names)


def picture(res: dict, path: Path) -> None:
    """Phantoms in front (x) against misses (y, log), one point per row, for the whole map and inside the
    public code's box; OASIS marked, the evidence rule's bright_share frontier joined."""
    fig, axes = common.pyplot().subplots(1, 2, figsize=(13, 5.5), dpi=90)
    style = {"rule": ("o", "#1f77b4", "gpumap rule"), "surface": ("s", "#9467bd", "surface layer"),
             "oasis": ("*", "#d62728", "public OASIS reconstruction")}
    for ax, key, where in zip(axes, ("judge", "judge_box"), ("whole map", "inside the public code's box"),
                              strict=True):
        colours = ("#2ca02c", "#ff7f0e", "#8c564b", "#e377c2")
        for (rule, fixed, option, _), colour in zip(FRONTIERS, colours, strict=False):
            front = sorted((r for r in res["rows"] if r["kind"] == "rule" and r["rule"] == rule
                            and set(r["options"]) <= {*fixed, option}
                            and all(r["options"].get(k) == v for k, v in fixed.items())),
                           key=lambda r: r[key]["phantom_rate"])
            if len(front) > 1:
                held = "".join(f", {k}={v}" for k, v in fixed.items())
                ax.plot([100 * r[key]["phantom_rate"] for r in front],
                        [100 * r[key]["missing_rate"] for r in front], "-", color=colour, alpha=0.5,
                        zorder=1, label=f"{rule} rule{held}, other {option}")
        seen: set[str] = set()
        oasis_offsets = iter([(9, -13, "left"), (-9, 5, "right"), (-9, 7, "right"), (-9, -15, "right")] * 4)
        at: dict[tuple[float, float], list[str]] = {}  # rows on one point share one label
        for r in res["rows"]:
            mk, c, kind = style[r["kind"]]
            x, y = 100 * r[key]["phantom_rate"], 100 * r[key]["missing_rate"]
            ax.scatter([x], [y], marker=mk, s=220 if r["kind"] == "oasis" else 60, color=c, zorder=3,
                       edgecolors="black" if r.get("default") else "none", linewidths=1.5,
                       label=None if kind in seen else kind)
            seen.add(kind)
            if r["kind"] == "oasis":
                dx, dy, ha = next(oasis_offsets)
                ax.annotate(r["name"], (x, y), textcoords="offset points", fontsize=7, color="#a01010", ha=ha,
                            xytext=(dx, dy))
            else:
                at.setdefault((round(x, 1), round(y, 2)), []).append(_short(r))
        for (x, y), names in at.items():
            ax.annotate(_joined(names), (x, y), textcoords="offset points", fontsize=7, xytext=(6, 3))
        ax.set(xlabel="phantoms in front, % of held-out beams with a return",
               ylabel="missing, % of held-out beams with a return (log)", yscale="log",
               title=where)
        ax.set_xlim(0, 1.4 * max(100 * r[key]["phantom_rate"] for r in res["rows"]))
        y0, y1 = ax.get_ylim()
        ticks = [t for t in (1, 2, 3, 4, 6, 10, 15, 20, 30, 40, 60, 100) if y0 <= t <= y1]
        ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
        ax.set_yticks([], minor=True)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    fig.suptitle(f"real tank: frames 0-799 mapped at every frame, {res['judged_frames']} held-out frames of "
                 f"800-1222 judged by first returns ({100 * res['voxel_size_m']:g} cm)", fontsize=10)
    common.save_figure(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
