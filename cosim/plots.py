"""`cosim plot OUT`: PNGs of one run or many (study replicas, sweeps) found under OUT.

    travel_sinkage.png   travel distance and sinkage over time (the paper's figures 2-4);
                         replicas overlaid, one colour per group (precision or sweep point)
    slip_drawbar.png     slip and drawbar pull over time
    drawbar_slip.png     mean drawbar pull against mean slip, one point per run (>= 2 runs)
"""

from __future__ import annotations

import json
import os

import numpy as np

from .output import RESULTS_FILE, read_series


def find_results(out_dir: str) -> list[str]:
    """All results.h5 files under out_dir (itself included), sorted."""
    found = []
    for root, dirs, files in os.walk(out_dir):
        dirs.sort()
        if RESULTS_FILE in files:
            found.append(os.path.join(root, RESULTS_FILE))
    return sorted(found)


def _group(path: str, attrs: dict, out_dir: str) -> str:
    relative = os.path.relpath(os.path.dirname(path), out_dir)
    parts = [p for p in relative.split(os.sep) if p not in (".", "")]
    if parts and parts[-1].startswith("replica_"):
        parts = parts[:-1]
    return "/".join(parts) if parts else str(attrs.get("name", "run"))


def plot_output(out_dir: str, plot_dir: str | None = None, dpi: int = 120) -> list[str]:
    """Write the PNGs for everything under out_dir; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = find_results(out_dir)
    if not paths:
        raise FileNotFoundError(f"no {RESULTS_FILE} under {out_dir!r}: run `cosim run SCENE --out {out_dir}` first")
    plot_dir = plot_dir or os.path.join(out_dir, "plots")
    os.makedirs(plot_dir, exist_ok=True)
    runs = []
    for path in paths:
        try:
            series = read_series(path)
        except Exception as error:  # a broken file must not stop the plots of the others
            print(f"skipping {path}: {error}")
            continue
        runs.append((path, _group(path, series["attrs"], out_dir), series))
    groups = sorted({g for _, g, _ in runs})
    colours = {g: plt.cm.tab10(i % 10) for i, g in enumerate(groups)}
    counts = {g: sum(1 for _, h, _ in runs if h == g) for g in groups}
    written = []

    def overlay(panels, name, title):
        fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.2), squeeze=False)
        for ax, (key, label, scale) in zip(axes[0], panels):
            seen = set()
            for _, group, s in runs:
                if len(s["time"]) == 0:
                    continue
                alpha = 0.9 if counts[group] == 1 else max(0.25, 1.0 / np.sqrt(counts[group]))
                ax.plot(s["time"], s[key][:, 0] * scale, color=colours[group], lw=1.2, alpha=alpha,
                        label=None if group in seen else f"{group} ({counts[group]})" if counts[group] > 1 else group)
                seen.add(group)
            ax.set_xlabel("time [s]")
            ax.set_ylabel(label)
            ax.grid(True, alpha=0.3)
            if len(groups) > 1 or any(c > 1 for c in counts.values()):
                ax.legend(fontsize=8)
        fig.suptitle(title)
        fig.tight_layout()
        path = os.path.join(plot_dir, name)
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)

    title = _title(runs)
    overlay([("travel", "travel distance [mm]", 1e3), ("sinkage", "sinkage [mm]", 1e3)], "travel_sinkage.png", title)
    overlay([("slip", "slip [-]", 1.0), ("drawbar_pull", "drawbar pull [N]", 1.0)], "slip_drawbar.png", title)
    if len(runs) >= 2:
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for _, group, s in runs:
            n = len(s["time"])
            if n == 0:
                continue
            tail = slice(n // 2, n)
            ax.scatter(np.mean(s["slip"][tail, 0]), np.mean(s["drawbar_pull"][tail, 0]), color=colours[group], s=18)
        for g in groups:
            ax.scatter([], [], color=colours[g], label=g)
        ax.set_xlabel("mean slip (second half) [-]")
        ax.set_ylabel("mean drawbar pull [N]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = os.path.join(plot_dir, "drawbar_slip.png")
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)
    return written


def _title(runs) -> str:
    if not runs:
        return ""
    attrs = runs[0][2]["attrs"]
    gravity = np.linalg.norm(np.asarray(attrs.get("gravity", [0, 0, 0]), dtype=float))
    name = attrs.get("name", "")
    return f"{name}: |g| = {gravity:.3g} m/s^2, {len(runs)} run(s)"


def plot_table(rows: list[dict], keys: list[str]) -> str:
    """A plain-text table (studies print it)."""
    widths = [max(len(k), *(len(_fmt(r.get(k))) for r in rows)) for k in keys]
    lines = ["  ".join(k.ljust(w) for k, w in zip(keys, widths)), "  ".join("-" * w for w in widths)]
    for r in rows:
        lines.append("  ".join(_fmt(r.get(k)).ljust(w) for k, w in zip(keys, widths)))
    return "\n".join(lines)


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (dict, list)):
        return json.dumps(value)
    return str(value)
