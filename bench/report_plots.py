"""The sweep's plots (PNG next to the results): speed against false negatives, images/s against
voxel size, scaling."""

from __future__ import annotations

from pathlib import Path

from .common import OASIS_PUBLISHED_MS, PAPER_TABLE_I, SONAR_RATE_HZ, TARGETS
from .report_sweep import _is_gpu, _series


def _plots(results: list[dict], out_dir: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    names = []
    markers = {0.06: "o", 0.05: "s", 0.04: "^", 0.03: "D", 0.02: "v", 0.01: "P", 0.005: "*"}
    # 1. speed vs false negatives
    fig, ax = plt.subplots(figsize=(9, 5.5))
    series: dict[str, list] = {}
    for res in results:
        for r in res["rows"]:
            if "images_per_s" in r and r.get("false_negative_rate") is not None and "quality_from" not in r:
                series.setdefault(_series(res, r), []).append(r)
    cmap = plt.get_cmap("tab20")
    for i, (name, rs) in enumerate(sorted(series.items())):
        rs = sorted(rs, key=lambda r: r["voxel_size_m"])
        c = cmap(i % 20)
        ax.plot(
            [r["images_per_s"] for r in rs],
            [100 * r["false_negative_rate"] for r in rs],
            "-",
            color=c,
            lw=0.8,
            alpha=0.6,
        )
        for r in rs:
            ax.plot(
                r["images_per_s"],
                100 * r["false_negative_rate"],
                markers.get(r["voxel_size_m"], "x"),
                color=c,
                ms=6,
            )
        ax.plot([], [], "-", color=c, label=name)
    for v, mk in markers.items():
        ax.plot([], [], mk, color="gray", label=f"{v * 100:g} cm")
    ax.axvline(SONAR_RATE_HZ, color="k", ls="--", lw=0.8)
    ax.set(
        xscale="log",
        xlabel="images per second (log)",
        ylabel="false-negative rate (%)",
        title="Speed against false negatives, same tank pings",
    )
    ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(out_dir / "speed_vs_fn.png", dpi=75)
    plt.close(fig)
    names.append("speed_vs_fn.png")

    # 2. Hz vs voxel size against Table I
    fig, ax = plt.subplots(figsize=(9, 5.5))
    for i, (name, rs) in enumerate(sorted(series.items())):
        rs = sorted(rs, key=lambda r: r["voxel_size_m"])
        ax.plot(
            [100 * r["voxel_size_m"] for r in rs],
            [r["images_per_s"] for r in rs],
            "o-",
            color=cmap(i % 20),
            ms=4,
            lw=1,
            label=name,
        )
    for res in results:  # capped numpy rows still have speeds
        for r in res["rows"]:
            if "quality_from" in r:
                ax.plot(100 * r["voxel_size_m"], r["images_per_s"], "x", color="gray", ms=5)
    tv = sorted(PAPER_TABLE_I)
    ax.plot(
        [100 * v for v in tv],
        [1 / PAPER_TABLE_I[v] for v in tv],
        "k-s",
        lw=2,
        ms=5,
        label="paper Table I (published)",
    )
    ov = sorted(OASIS_PUBLISHED_MS)
    ax.plot(
        [100 * v for v in ov],
        [1e3 / OASIS_PUBLISHED_MS[v] for v in ov],
        "k:^",
        lw=1.5,
        ms=5,
        label="OASIS code (published, issue 6)",
    )
    ax.axhline(SONAR_RATE_HZ, color="r", ls="--", lw=1, label="10 Hz sonar rate")
    for dev, v, hz in TARGETS:
        ax.plot(
            100 * v,
            hz,
            "*",
            color="gold" if dev == "cpu" else "lime",
            ms=14,
            mec="k",
            label=f"target {dev.upper()}" if (dev, v) in (("cpu", 0.03), ("gpu", 0.01)) else None,
        )
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="voxel size (cm, log)",
        ylabel="images per second (log)",
        title="Update rate against voxel size",
    )
    ax.invert_xaxis()
    ticks = [6, 5, 4, 3, 2, 1, 0.5]
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(out_dir / "hz_vs_voxel.png", dpi=75)
    plt.close(fig)
    names.append("hz_vs_voxel.png")

    # 3. scaling
    fits = [(res, f) for res in results for f in res.get("scaling", {}).get("voxels_in_view_fit", [])]
    ims = [
        (res, r) for res in results for r in res.get("scaling", {}).get("image_size", []) if "error" not in r
    ]
    ekf = [r for res in results for r in res.get("scaling", {}).get("ekf", [])]
    if fits or ims or ekf:
        fig, axs = plt.subplots(1, 3, figsize=(13, 4))
        import numpy as np

        for i, (_, f) in enumerate(fits):
            x = np.array(f["voxels_in_view"])
            c = cmap(i % 20)
            axs[0].plot(x, f["ms_median"], "o", color=c, ms=4, label=f"{f['backend']} {f['method']}")
            xx = np.linspace(x.min(), x.max(), 50)
            axs[0].plot(xx, f["ms_fixed"] + f["ns_per_voxel"] * 1e-6 * xx, "-", color=c, lw=0.8)
        axs[0].set(
            xscale="log",
            yscale="log",
            xlabel="voxels in view per ping",
            ylabel="median ms per image",
            title="cost vs voxels in view (lines: linear fit)",
        )
        if fits:
            axs[0].legend(fontsize=6)
        groups: dict[str, list] = {}
        for _, r in ims:
            groups.setdefault(f"{r['backend']}" + (" [GPU]" if _is_gpu(r) else ""), []).append(r)
        for name, rs in sorted(groups.items()):
            rs = sorted(rs, key=lambda r: r["pixels"])
            axs[1].plot([r["pixels"] for r in rs], [r["ms_median"] for r in rs], "o-", ms=4, label=name)
        axs[1].set(
            xscale="log",
            yscale="log",
            xlabel="pixels per image (bins x beams)",
            ylabel="median ms",
            title="cost vs image size (3 cm, gather)",
        )
        axs[1].legend(fontsize=6)
        if ekf:
            axs[2].plot(
                [r["n_features"] for r in ekf], [r["update_us_median"] for r in ekf], "o-", label="update"
            )
            axs[2].plot(
                [r["n_features"] for r in ekf], [r["predict_us_median"] for r in ekf], "s-", label="predict"
            )
            one = [r for res in results for r in res.get("scaling", {}).get("ekf_one_blas_thread", [])]
            if one:
                axs[2].plot(
                    [r["n_features"] for r in one],
                    [r["update_us_median"] for r in one],
                    "o--",
                    label="update, 1 BLAS thread",
                )
            axs[2].set(
                xscale="log",
                yscale="log",
                xlabel="features in the state",
                ylabel="µs",
                title="EKF cost vs features",
            )
            axs[2].legend(fontsize=7)
        for a in axs:
            a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            a.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        fig.tight_layout()
        fig.savefig(out_dir / "scaling.png", dpi=70)
        plt.close(fig)
        names.append("scaling.png")
    return names


