"""``python -m bench.distance``: the distance field of the safe map on the real tank, beside SciPy.

Three measurements (issue 44), on the full-rate OASIS tank run (frames 0-799 by default: the development
split), mapped with the default evidence rule at ``--threshold``:

- **full**: the whole field of the tank at 2 cm (``--full-voxel``), per backend: best of ``--repeats`` of
  the transform from the obstacle mask to float32 metres, beside ``scipy.ndimage.distance_transform_edt``
  (``sampling`` the voxel size) on the same mask, the largest difference to it, and the whole
  ``DistanceField.update(full=True)`` (the map read included); unknown voxels as obstacles and as free.
- **block**: a local 2 m cube at 1 cm (``--block-size``, ``--block-voxel``) around the occupied voxels'
  centroid, mapped from every ``--block-stride``-th frame into that box: the same figures.
- **incremental**: at 5 cm (``--inc-voxel``), after every batch of ``--batch`` pings, ``update()``
  against ``update(full=True)`` on the same map (must be equal, voxel for voxel, every batch): the mean
  ratio of their times, the mean ratio without the map read (``mapper.values()``, timed apart: both
  pay it), and the share of the transform's work that was rerun; per backend and obstacle setting.

``--save-states FILE`` keeps the maps' voxel states (occupied, free, unknown: 2 bits a voxel) and
``--states FILE`` replays them without the recording or a mapper (a machine with a GPU and no data:
the read is then a decode, not the mapper's). Writes ``bench/results/distance.json``.

``python -m bench.report`` renders every ``bench/results/distance*.json`` into BENCHMARKS.md
(:data:`SECTION`): these runs and the node's latency with the field off and on
(``python -m bench.ros_bench --distance`` ->
``distance_node.json``).
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import (
    GPU_BACKENDS,
    CpuShare,
    Section,
    bench_parser,
    load_average,
    oasis_full_dir,
    run_header,
    spread,
    write_json,
)
from .common import fnum as _f

SCHEMA = "gpumap-distance/1"
CONFIGS = ({"unknown_is_obstacle": True}, {"unknown_is_obstacle": False},
           {"unknown_is_obstacle": False, "max_distance_m": 0.5})


class StateMap:
    """A map replayed from voxel states: the four things the layer reads (``values``: 0.9 occupied, 0
    free, NaN unknown)."""

    def __init__(self, grid, states: np.ndarray, threshold: float, backend: str) -> None:
        self.grid, self.threshold, self.backend = grid, threshold, backend
        self.set(states)

    def set(self, states: np.ndarray) -> None:
        self.v = np.where(states == 2, np.float32(0.9), np.float32(0.0))
        self.v[states == 0] = np.nan

    def values(self) -> np.ndarray:
        return self.v.copy()


def states_of(values: np.ndarray, threshold: float) -> np.ndarray:
    """uint8 voxel states: 0 unknown, 1 free, 2 occupied."""
    s = np.ones(values.shape, np.uint8)
    s[np.isnan(values)] = 0
    s[values >= np.float32(threshold)] = 2
    return s


def _pack(states: np.ndarray) -> np.ndarray:
    return np.packbits(np.stack([states == 0, states == 2]).reshape(-1))


def _unpack(packed: np.ndarray, shape) -> np.ndarray:
    n = int(np.prod(shape))
    bits = np.unpackbits(packed)[: 2 * n].reshape(2, n)
    s = np.ones(n, np.uint8)
    s[bits[0] == 1] = 0
    s[bits[1] == 1] = 2
    return s.reshape(shape)


def _grid_dict(g) -> dict:
    return {**g.to_dict(), "shape": list(g.shape), "voxels": g.n_voxels}


def _frames(path: Path, start: int, stop: int):
    from gpumap.io import open_recording

    rec = open_recording(path)
    imgs, poses, spec = [], [], None
    for i, f in enumerate(rec):
        if i >= stop:
            break
        if i >= start:
            imgs.append(f.image)
            poses.append(f.T_W_S)
            spec = f.spec
    return spec, np.stack(imgs), np.stack(poses)


def _mapper(spec, grid, backend: str, threshold: float):
    import gpumap

    return gpumap.MinMaxMapper(spec, grid, backend, MapperParams(threshold=threshold))


def _map(m, imgs, poses, batch: int = 32):
    for a in range(0, len(imgs), batch):
        m.integrate_batch(imgs[a:a + batch], poses[a:a + batch])
    m.synchronize()
    return m


def _best(fn, repeats: int) -> tuple[dict, object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return {"best_s": min(times), **{f"{k}_s": v for k, v in spread(times).items()}}, out


def _scipy(mask: np.ndarray, voxel: float, cap: float | None) -> np.ndarray:
    from scipy import ndimage

    if mask.all() or not mask.any():
        return np.full(mask.shape, 0.0 if mask.all() else np.inf)
    d = ndimage.distance_transform_edt(~mask, sampling=voxel)
    return d if cap is None else np.minimum(d, cap)


def field_rows(source, backends: list[str], repeats: int, live: bool) -> dict:
    """The full field of ``source`` (a mapper or a :class:`StateMap`) per obstacle setting: SciPy, and per
    backend the transform from the mask and the whole full update."""
    from gpumap.layers.distance import DistanceField, cap_squared, d2_to_metres
    from gpumap.layers.distance_device import make_transform

    g = source.grid
    s = g.voxel_size_m
    out = {"grid": _grid_dict(g), "settings": []}
    for unknown in (True, False):
        df0 = DistanceField(source, unknown_is_obstacle=unknown, backend="numpy")
        mask = df0.obstacles()
        sc, ref = _best(lambda mask=mask: _scipy(mask, s, None), repeats)
        row = {"unknown_is_obstacle": unknown, "obstacle_share": float(mask.mean()), "scipy": sc,
               "backends": {}}
        del df0
        for name in backends:
            tr = make_transform(name)
            cap2 = cap_squared(None, s)

            def run(tr=tr, mask=mask, cap2=cap2):
                return d2_to_metres(tr(mask, cap2)[0], s, cap2, None)

            if name != "numpy":
                run()  # warm: kernels loaded, buffers allocated
            t, f = _best(run, repeats)
            err = float(np.max(np.abs(f.astype(np.float64) - ref))) if np.isfinite(ref).all() else None
            r = {"transform": t, "max_abs_err_vs_scipy_m": err, "device": tr.device,
                 "speedup_vs_scipy": sc["best_s"] / t["best_s"]}
            del f, tr
            df = DistanceField(source, unknown_is_obstacle=unknown, backend=name)
            r["update_full"], _ = _best(lambda df=df: df.update(full=True), repeats)
            r["update_full"]["read"] = "mapper.values()" if live else "states decode"
            del df
            row["backends"][name] = r
        out["settings"].append(row)
    return out


def incremental_rows(grid, sequence, threshold: float, backends: list[str], live_mapper=None) -> dict:
    """``update()`` against ``update(full=True)`` after every state of ``sequence`` (an iterable of
    callables that bring the source to the next batch's map), per backend and setting."""
    from gpumap.layers.distance import DistanceField

    source = live_mapper
    if source is None:
        source = StateMap(grid, np.zeros(grid.shape, np.uint8), threshold, "numpy")
    fields = {(b, i): DistanceField(source, backend=b, **c) for b in backends for i, c in enumerate(CONFIGS)}
    rec = {k: {"ratio": [], "transform_ratio": [], "work": [], "equal": []} for k in fields}
    n_batches = 0
    for step in sequence:
        step(source)
        n_batches += 1
        t = time.perf_counter()
        source.values()
        read = time.perf_counter() - t
        for k, df in fields.items():
            t = time.perf_counter()
            n = df.update()
            t_inc = time.perf_counter() - t
            f = df.field()
            t = time.perf_counter()
            df.update(full=True)
            t_full = time.perf_counter() - t
            r = rec[k]
            r["ratio"].append(t_inc / t_full)
            r["transform_ratio"].append(max(t_inc - read, 0.0) / max(t_full - read, 1e-9))
            r["work"].append(n / grid.n_voxels)
            r["equal"].append(bool(np.array_equal(f, df.field())))
    rows = []
    for (b, i), r in rec.items():
        df = fields[(b, i)]
        ref = _scipy(df.obstacles(), grid.voxel_size_m, CONFIGS[i].get("max_distance_m"))
        err = float(np.max(np.abs(df.field() - ref))) if np.isfinite(ref).all() else None
        rows.append({"backend": b, **CONFIGS[i], "batches": n_batches,
                     "mean_ratio": float(np.mean(r["ratio"])),
                     "mean_transform_ratio": float(np.mean(r["transform_ratio"])),
                     "mean_work_share": float(np.mean(r["work"])), "equal_every_batch": all(r["equal"]),
                     "final_max_abs_err_vs_scipy_m": err,
                     "per_batch": {k: [round(x, 4) for x in v] for k, v in r.items() if k != "equal"}})
    return {"grid": _grid_dict(grid), "rows": rows}


# ------------------------------------------------------------------------------ BENCHMARKS.md
#: The issue's target: an incremental update costs at most this share of a full one, on average.
TARGET_RATIO = 0.25
_CONFIG_LABELS = ("unknown = obstacle", "unknown = free", "unknown = free, cap 0.5 m")


def _config(row: dict) -> int:
    return next(i for i, c in enumerate(CONFIGS)
                if row["unknown_is_obstacle"] == c["unknown_is_obstacle"]
                and row.get("max_distance_m") == c.get("max_distance_m"))


def _load(x) -> str:
    return "/".join(f"{v:.1f}" for v in x) if x else "?"


def _run_line(name: str, d: dict) -> str:
    m, share = d.get("machine", {}), d.get("cpu_share") or {}
    gpus = ", ".join(m.get("gpus") or []) or "no GPU"
    others = ("" if share.get("others_cores") is None
              else f", other processes {share['others_cores']:.2f} cores")
    return (f"- `{name}` ({d.get('created', '?')}): {m.get('cpu_model', '?')}, {m.get('cpu_count', '?')} "
            f"cores, {gpus}; load {_load(d.get('load_avg_before'))} at the start, "
            f"{_load(d.get('load_avg_after'))} at the end{others}; commit `{(d.get('commit') or '?')[:7]}`; "
            f"`python -m bench.distance {' '.join(d.get('argv') or [])}`; "
            f"{_f(share.get('wall_s'), '.0f')} s")


def _field_table(docs: list[tuple[str, dict]]) -> list[str]:
    out = ["| grid | voxels | unknown | obstacles | SciPy s | backend | transform s | x SciPy "
           "| full update s | max abs err vs SciPy (m) | file |",
           "|---|---:|---|---:|---:|---|---:|---:|---:|---:|---|"]
    for name, d in docs:
        for key, what in (("full", "tank"), ("block", "2 m block")):
            sec = d.get(key)
            if sec is None:
                continue
            g = sec["grid"]
            grid = f"{what} at {g['voxel_size_m'] * 100:g} cm, {' x '.join(map(str, g['shape']))}"
            for st in sec["settings"]:
                unk = "obstacle" if st["unknown_is_obstacle"] else "free"
                for b, r in st["backends"].items():
                    out.append(f"| {grid} | {g['voxels']:,} | {unk} | {100 * st['obstacle_share']:.1f} % "
                               f"| {st['scipy']['best_s']:.2f} | {b} | {r['transform']['best_s']:.3f} "
                               f"| {r['speedup_vs_scipy']:.1f} | {r['update_full']['best_s']:.3f} "
                               f"| {_f(r['max_abs_err_vs_scipy_m'], '.1e')} | `{name}` |")
    return out


def _incremental(docs: list[tuple[str, dict]]) -> tuple[list[str], list[str]]:
    """The incremental table and one verdict line per file against :data:`TARGET_RATIO`."""
    out = ["| file | batch (pings) | batches | backend | " + " | ".join(_CONFIG_LABELS)
           + " | equal to a full update every batch |",
           "|---|---:|---:|---|" + "---|" * len(_CONFIG_LABELS) + "---|"]
    verdicts = []
    for name, d in docs:
        inc = d.get("incremental")
        if inc is None:
            continue
        rows = inc["rows"]
        for b in dict.fromkeys(r["backend"] for r in rows):
            cells = ["–"] * len(CONFIGS)
            mine = [r for r in rows if r["backend"] == b]
            for r in mine:
                cells[_config(r)] = (f"{r['mean_ratio']:.2f} / {r['mean_transform_ratio']:.2f} / "
                                     f"{r['mean_work_share']:.2f}")
            eq = "yes" if all(r["equal_every_batch"] for r in mine) else "**NO**"
            out.append(f"| `{name}` | {inc['batch']} | {mine[0]['batches']} | {b} | " + " | ".join(cells)
                       + f" | {eq} |")
        dev = [r for r in rows
               if r["backend"] != "numpy" and (r["unknown_is_obstacle"] or r.get("max_distance_m"))]
        if not dev:
            continue
        lo, hi = min(r["mean_ratio"] for r in dev), max(r["mean_ratio"] for r in dev)
        tlo, thi = min(r["mean_transform_ratio"] for r in dev), max(r["mean_transform_ratio"] for r in dev)
        met = "**met**" if hi <= TARGET_RATIO else "**not met**" if lo > TARGET_RATIO else "met by some rows"
        tmet = "met" if thi <= TARGET_RATIO else "not met" if tlo > TARGET_RATIO else "met by some rows"
        free = [r["mean_ratio"] for r in rows if r["backend"] != "numpy" and not r["unknown_is_obstacle"]
                and not r.get("max_distance_m")]
        numpy = [r["mean_ratio"] for r in rows if r["backend"] == "numpy"]
        names = ", ".join(dict.fromkeys(r["backend"] for r in dev))
        verdicts.append(
            f"- Batches of {inc['batch']} pings (`{name}`, {names}, unknown as obstacle or capped): an "
            f"update costs **{lo:.2f}-{hi:.2f}** of a full one on average, "
            f"the map read included: the target of {TARGET_RATIO:g} is {met}; without the read (both pay it) "
            f"{tlo:.2f}-{thi:.2f}, {tmet}"
            + (f". Unknown as free without a cap: {min(free):.2f}-{max(free):.2f}" if free else "")
            + (f"; the NumPy path (boxes): {min(numpy):.2f}-{max(numpy):.2f}" if numpy else "") + ".")
    return out, verdicts


def _node_lines(docs: list[tuple[str, dict]]) -> list[str]:
    out = []
    for name, d in docs:
        m = d.get("machine", {})
        out += ["", common.template("distance-node", file=name, created=d.get("created", "?"),
                                    cpu=f"{m.get('cpu_model', '?')} x{m.get('cpu_count', '?')}",
                                    commit=((m.get("git") or {}).get("commit") or "?")[:7],
                                    argv=" ".join(d.get("argv") or [])), "",
                "| voxel | rate (Hz) | field | play | mapped | lost | cloud latency p50 / p99 ms "
                "| node's own p50 / p99 ms | distance cloud p50 / p99 ms | field updates / published "
                "| field update ms (mean) | load before / after |",
                "|---:|---:|---|---:|---:|---|---:|---:|---:|---:|---:|---|"]
        for r in d["runs"]:
            lost = ", ".join(f"{k} {v}" for k, v in r["lost"].items()) or "none"
            la = r.get("load_avg") or []
            dist = "–"
            if r["distance"]:
                dist = " / ".join(_f(r[f"distance_latency_ms_p{q}"], ".1f") for q in (50, 99))
            upd, mean = "–", "–"
            if r["distance"]:
                upd = f"{r.get('distance_updates')} / {r.get('distance_changes')}"
                n, sec = int(r.get("distance_updates") or 0), float(r.get("distance_seconds") or "nan")
                mean = _f(1e3 * sec / n if n else None, ".1f")
            out.append(f"| {r['voxel_size_m'] * 100:g} cm | {r['requested_hz']:g} "
                       f"| {'on' if r['distance'] else 'off'} | {r['repeat'] + 1} | {r['integrated']} "
                       f"| {lost} "
                       f"| {_f(r['latency_ms_p50'], '.1f')} / {_f(r['latency_ms_p99'], '.1f')} "
                       f"| {_f(r['node_latency_ms_p50'], '.1f')} / {_f(r['node_latency_ms_p99'], '.1f')} "
                       f"| {dist} | {upd} | {mean} "
                       f"| {_load(la[:3])} / {_load(la[3:])} |")
        for vs in sorted({r["voxel_size_m"] for r in d["runs"]}):
            for hz in sorted({r["requested_hz"] for r in d["runs"]}):
                med = {on: [r["node_latency_ms_p50"] for r in d["runs"] if r["distance"] == on
                            and r["voxel_size_m"] == vs and r["requested_hz"] == hz] for on in (False, True)}
                if med[False] and med[True]:
                    a, b = float(np.median(med[False])), float(np.median(med[True]))
                    out += ["", f"At {vs * 100:g} cm and {hz:g} Hz the node's own latency (arrival to "
                            f"published map, median of the plays' p50) is {a:.1f} ms with the field off and "
                            f"{b:.1f} ms with it on: **{b - a:+.1f} ms**."]
    return out


def markdown(docs: list[tuple[str, dict]], folder: Path) -> str:
    """The BENCHMARKS.md block of every ``distance*.json`` (every figure read from them)."""
    field = [(n, d) for n, d in docs if d.get("schema") == SCHEMA]
    node = [(n, d) for n, d in docs if d.get("schema") == "gpumap-distance-node/1"]
    out = [common.template("distance-intro"), "", *(_run_line(n, d) for n, d in field), ""]
    out += _field_table(field)
    inc, verdicts = _incremental(field)
    out += ["", common.template("distance-incremental"), "", *inc, "", *verdicts]
    gpu = set()
    for _, d in field:
        for key in ("full", "block"):
            gpu |= {b for st in (d.get(key) or {}).get("settings", []) for b in st["backends"]}
        gpu |= {r["backend"] for r in (d.get("incremental") or {}).get("rows", [])}
    gpu &= set(GPU_BACKENDS)
    out += ["", f"GPU rows: {', '.join(sorted(gpu))}, in the tables above." if gpu
            else common.template("distance-no-gpu")]
    if node:
        out += _node_lines(node)
    else:
        out += ["", "Not measured yet: the node's latency with the field on and off "
                "(`python -m bench.ros_bench --distance --rates 20 --voxel-size 0.05`)."]
    return "\n".join(out).rstrip("\n")


SECTION = Section("distance", "## The distance field of the safe map (issue 44)", "distance*.json", markdown)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("distance", __doc__, out="bench/results/distance.json", backend=[], progress=True)
    ap.add_argument("--data", type=Path, default=None, help="the full run's recording folder")
    ap.add_argument("--frames", type=int, nargs=2, default=(0, 800), metavar=("START", "STOP"),
                    help="frames mapped (default 0 800: the development split)")
    ap.add_argument("--threshold", type=float, default=0.4, help="bright / occupied (default 0.4)")
    ap.add_argument("--map-backend", default="auto", help="the mapper's backend (default auto)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--full-voxel", type=float, default=0.02)
    ap.add_argument("--full-stride", type=int, default=1, help="every N-th frame for the full field's map")
    ap.add_argument("--block-voxel", type=float, default=0.01)
    ap.add_argument("--block-size", type=float, default=2.0, help="the local block's edge, metres")
    ap.add_argument("--block-stride", type=int, default=4, help="every N-th frame for the block's map")
    ap.add_argument("--inc-voxel", type=float, default=0.05)
    ap.add_argument("--batch", type=int, default=32, help="pings per update in the incremental run")
    ap.add_argument("--sections", nargs="+", default=["full", "block", "incremental"],
                    choices=["full", "block", "incremental"])
    ap.add_argument("--save-states", type=Path, default=None, help="keep the maps' voxel states here (.npz)")
    ap.add_argument("--states", type=Path, default=None, help="replay voxel states saved by --save-states")
    a = ap.parse_args(argv)
    from gpumap.backends import available_backends
    from gpumap.spec import GridSpec, auto_grid

    backends = a.backend or [b for b in available_backends() if b != "opencl"]
    doc = run_header(SCHEMA, argv) | {
        "platform": platform.platform(), "cpu_count": os.cpu_count(), "load_avg_before": load_average(),
        "commit": None, "backends": backends, "frames": list(a.frames), "threshold": a.threshold,
        "repeats": a.repeats}
    doc["commit"] = doc["machine"].get("git", {}).get("commit")
    saved, states = {}, None
    if a.states is not None:
        states = dict(np.load(a.states, allow_pickle=False))
        doc["states"] = str(a.states)
    else:
        data = a.data or oasis_full_dir()
        if data is None:
            raise SystemExit("bench.distance: the full tank run was not found (shared/data/README.md says "
                             "how to get it); pass --data, or --states")
        t0 = time.perf_counter()
        spec, imgs, poses = _frames(data, *a.frames)
        doc["data"] = {"path": str(data), "frames_read": len(imgs), "read_s": time.perf_counter() - t0}
    with CpuShare() as share:
        if "full" in a.sections:
            if states is None:
                g = auto_grid(spec, poses, a.full_voxel)
                t0 = time.perf_counter()
                m = _map(_mapper(spec, g, a.map_backend, a.threshold), imgs[::a.full_stride],
                         poses[::a.full_stride])
                mapping = {"stride": a.full_stride, "pings": len(imgs[::a.full_stride]), "backend": m.backend,
                           "seconds": time.perf_counter() - t0}
                saved["full"] = (g, states_of(m.values(), a.threshold))
                src, live = m, True
            else:
                g = GridSpec.from_dict(json.loads(str(states["full_grid"])))
                src = StateMap(g, _unpack(states["full"], g.shape), a.threshold, "numpy")
                mapping, live = {"from": "states"}, False
            print(f"full field: {g.shape} at {g.voxel_size_m} m", flush=True)
            doc["full"] = {"mapping": mapping, **field_rows(src, backends, a.repeats, live)}
            del src
        if "block" in a.sections:
            if states is None:
                occ = saved.get("full")
                c = (np.asarray(occ[0].centers(np.argwhere(occ[1] == 2))).mean(0) if occ is not None
                     else poses[:, :3, 3].mean(0))
                h = a.block_size / 2
                g = GridSpec(tuple(c - h), tuple(c + h), a.block_voxel)
                t0 = time.perf_counter()
                m = _map(_mapper(spec, g, a.map_backend, a.threshold), imgs[::a.block_stride],
                         poses[::a.block_stride])
                mapping = {"stride": a.block_stride, "pings": len(imgs[::a.block_stride]),
                           "backend": m.backend, "seconds": time.perf_counter() - t0, "center_m": c.tolist()}
                saved["block"] = (g, states_of(m.values(), a.threshold))
                src, live = m, True
            else:
                g = GridSpec.from_dict(json.loads(str(states["block_grid"])))
                src = StateMap(g, _unpack(states["block"], g.shape), a.threshold, "numpy")
                mapping, live = {"from": "states"}, False
            print(f"block: {g.shape} at {g.voxel_size_m} m", flush=True)
            doc["block"] = {"mapping": mapping, **field_rows(src, backends, a.repeats, live)}
            del src
        if "incremental" in a.sections:
            if states is None:
                g = auto_grid(spec, poses, a.inc_voxel)
                m = _mapper(spec, g, a.map_backend, a.threshold)
                seq_states = []

                def steps():
                    for b0 in range(0, len(imgs), a.batch):
                        def step(mm, b0=b0):
                            mm.integrate_batch(imgs[b0:b0 + a.batch], poses[b0:b0 + a.batch])
                            mm.synchronize()
                            seq_states.append(_pack(states_of(mm.values(), a.threshold)))
                        yield step

                print(f"incremental: {g.shape} at {g.voxel_size_m} m, batches of {a.batch}", flush=True)
                doc["incremental"] = {"batch": a.batch, "read": "mapper.values()",
                                      **incremental_rows(g, steps(), a.threshold, backends, m)}
                saved["inc"] = (g, np.stack(seq_states))
            else:
                g = GridSpec.from_dict(json.loads(str(states["inc_grid"])))
                seq = states["inc"]

                def steps():
                    for row in seq:
                        yield lambda src, row=row: src.set(_unpack(row, g.shape))

                doc["incremental"] = {"batch": int(states["batch"]), "read": "states decode",
                                      **incremental_rows(g, steps(), a.threshold, backends)}
    doc["load_avg_after"] = load_average()
    doc["cpu_share"] = {"others_cores": share.others_cores, "bench_cores": share.own_cores,
                        "wall_s": share.wall_s}
    if a.save_states is not None and saved:
        out = {"batch": np.int64(a.batch)}
        for key, (g, s) in saved.items():
            out[f"{key}_grid"] = np.array(json.dumps(g.to_dict()))
            out[key] = s if key == "inc" else _pack(s)
        a.save_states.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(a.save_states, **out)
    write_json(a.out, doc, digits=4)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
