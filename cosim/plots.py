"""`cosim plot OUT`: PNGs of one run or many (replicas, studies, sweeps) found under OUT.

travel_sinkage.png   travel and sinkage (rim and grouser tips) over time (the paper's figures 2-4);
                     replicas overlaid, one colour per group; the steady-state window shaded
slip_drawbar.png     slip and drawbar pull over time
drawbar_slip.png     steady-state drawbar pull against slip, one point per run (>= 2 runs)
trajectory.png       (rovers) the rover body's path seen from above, and its travel and slip over time
wheels.png           (rovers) slip, sinkage, driving torque and power of every wheel over the drive
scatter.png          (studies) mean, std and min-max of the metrics per group
dbp_slip.png         (slip study) DP/W, torque and sinkage against imposed slip with 95 % intervals
"""

from __future__ import annotations

import json
import logging
import os

import numpy as np

from soil.errors import ArgumentError, DamagedFileError
from soil.files import atomic_path, output_target

from .folders import PLOTS_DIR, RESULTS_FILE
from .output import check_results, read_series, stored_summary
from .single_wheel import PHASE_DRIVING

log = logging.getLogger(__name__)


SEARCH_DEPTH = 4
"""How many folders below OUT `cosim plot` looks for runs [count]: the deepest the project writes is a
study's FOLDER/slip_x/replica_k (2), kept in a folder of studies (3) and one more level; a folder
such as / or /tmp is not walked to its bottom."""


RUN_PICTURES = ("travel_sinkage.png", "slip_drawbar.png", "drawbar_slip.png")
"""The pictures `plot_output` may write in its folder for any run (module docstring; the last of two or more)."""
ROVER_PICTURES = ("trajectory.png", "wheels.png")
"""... and for rover runs."""


def save_figure(fig, path: str, dpi: float, replace: bool = True) -> None:
    """Save a matplotlib figure to `path` whole or not at all, in the format its extension names: written
    beside it under a temporary name, then renamed (soil.files.atomic_path), so a crash, a signal or a full
    disk never leaves half a picture, nor spoils the one already there; a missing folder is made.

    replace False: a file that appeared at `path` while the figure was drawn is kept, the picture written
    beside it (FileExistsError naming both: soil.files.place_new). `path` a symbolic link is written through
    (its file replaced, the link kept) only when that file's name ends in the same format: a link
    travel_sinkage.png -> results.h5 is refused (ArgumentError naming both), not written through."""
    kind = os.path.splitext(path)[1][1:].lower()
    if not kind:
        raise ArgumentError(f"{path}: a picture's name ends in its format (.png, .pdf, .svg)")
    output_target(path, (f".{kind}",), what="the picture")
    with atomic_path(path, suffix=f".{kind}", replace=replace) as temporary, open(temporary, "wb") as out:
        fig.savefig(out, format=kind, dpi=dpi)


def find_results(out_dir: str) -> list[str]:
    """The results.h5 files in out_dir and up to SEARCH_DEPTH folders below it, sorted; hidden folders
    and plots/ folders are not entered."""
    found = []
    for root, dirs, files in os.walk(out_dir):
        relative = os.path.relpath(root, out_dir)
        depth = 0 if relative == os.curdir else relative.count(os.sep) + 1
        dirs[:] = [] if depth >= SEARCH_DEPTH else sorted(d for d in dirs if not d.startswith(".") and d != PLOTS_DIR)
        if RESULTS_FILE in files:
            found.append(os.path.join(root, RESULTS_FILE))
    return sorted(found)


def _group(path: str, attrs: dict, out_dir: str) -> str:
    relative = os.path.relpath(os.path.dirname(path), out_dir)
    parts = [p for p in relative.split(os.sep) if p not in (".", "")]
    if parts and parts[-1].startswith("replica_"):
        parts = parts[:-1]
    return "/".join(parts) if parts else str(attrs.get("name", "run"))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_output(out_dir: str, plot_dir: str | None = None, dpi: int = 120) -> list[str]:
    """Write the PNGs for everything under out_dir; returns their paths."""
    plt = _pyplot()
    paths = find_results(out_dir)
    if not paths:
        raise ArgumentError(
            f"no {RESULTS_FILE} under {out_dir!r} (looked {SEARCH_DEPTH} folders deep): run `cosim run SCENE "
            f"--out {out_dir}` first, or name the run's or study's folder"
        )
    plot_dir = plot_dir or os.path.join(out_dir, PLOTS_DIR)
    runs = []
    damaged = []
    for path in paths:
        try:
            check_results(path, data=False)  # a file not ours named as such (as `cosim view` and `export` do)
            series = read_series(path)
        except DamagedFileError as error:  # a broken file must not stop the plots of the others
            damaged.append(error)
            continue
        runs.append((path, _group(path, series["attrs"], out_dir), series))
    if not runs:  # nothing to plot: say why instead of writing empty figures
        extra = f" (and {len(damaged) - 1} more damaged file(s))" if len(damaged) > 1 else ""
        raise DamagedFileError(f"{damaged[0]}{extra}; no plot was written")
    for problem in damaged:
        log.warning("skipping %s", problem)
    rovers = [run for run in runs if run[2]["attrs"].get("kind") == "rover"]
    pictures = RUN_PICTURES if len(runs) >= 2 else RUN_PICTURES[:2]  # drawbar_slip.png: of two runs or more
    for name in pictures + (ROVER_PICTURES if rovers else ()):  # before the first picture is replaced:
        # a link it must not write through, or a folder
        if os.path.isdir(output_target(os.path.join(plot_dir, name), (".png",), what="the picture")):
            raise ArgumentError(f"the picture {os.path.join(plot_dir, name)!r} is a folder; a picture is a file")
    os.makedirs(plot_dir, exist_ok=True)
    groups = sorted({g for _, g, _ in runs})
    colours = {g: plt.cm.tab10(i % 10) for i, g in enumerate(groups)}
    counts = {g: sum(1 for _, h, _ in runs if h == g) for g in groups}
    written = []

    def overlay(panels, name):
        fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.2), squeeze=False)
        for ax, (key, label, scale, style) in zip(axes[0], panels):
            seen = set()
            for _, group, s in runs:
                if len(s["time"]) == 0:
                    continue
                alpha = 0.9 if counts[group] == 1 else max(0.25, 1.0 / np.sqrt(counts[group]))
                ax.plot(
                    s["time"],
                    s[key][:, 0] * scale,
                    style,
                    color=colours[group],
                    lw=1.2,
                    alpha=alpha,
                    label=None if group in seen else f"{group} ({counts[group]})" if counts[group] > 1 else group,
                )
                seen.add(group)
                window = stored_summary(s["attrs"]).get("window")
                if window and len(runs) == 1 and np.all(np.isfinite(window)):
                    ax.axvspan(window[0], window[1], color="0.85", zorder=0, label="steady-state window")
            ax.set_xlabel("time [s]")
            ax.set_ylabel(label)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
        fig.suptitle(_title(runs))
        fig.tight_layout()
        path = os.path.join(plot_dir, name)
        save_figure(fig, path, dpi)
        plt.close(fig)
        written.append(path)

    if rovers:
        written += _rover_plots(plt, rovers, colours, plot_dir, dpi)
    overlay(
        [
            ("travel", "travel [mm]", 1e3, "-"),
            ("sinkage", "rim sinkage [mm]", 1e3, "-"),
            ("sinkage_tips", "grouser-tip sinkage [mm]", 1e3, "-"),
        ],
        "travel_sinkage.png",
    )
    overlay(
        [
            ("slip", "slip [-]", 1.0, "-"),
            ("drawbar_pull", "drawbar pull [N]", 1.0, "-"),
            ("driving_torque", "driving torque [N m]", 1.0, "-"),
        ],
        "slip_drawbar.png",
    )
    if len(runs) >= 2:
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for _, group, s in runs:
            summary = stored_summary(s["attrs"])
            if summary.get("steady_state") == "steady":
                ax.scatter(summary["slip"], summary["drawbar_pull"], color=colours[group], s=18)
        for g in groups:
            ax.scatter([], [], color=colours[g], label=g)
        ax.set_xlabel("steady-state slip [-]")
        ax.set_ylabel("steady-state drawbar pull [N]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = os.path.join(plot_dir, "drawbar_slip.png")
        save_figure(fig, path, dpi)
        plt.close(fig)
        written.append(path)
    return written


def _rover_plots(plt, runs, colours, plot_dir: str, dpi: int) -> list[str]:
    """trajectory.png and wheels.png of rover runs (module docstring)."""
    written = []
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    for _, group, s in runs:
        driving = s["phase"] == PHASE_DRIVING
        xy = s["rover_position"][:, :2]
        colour = colours[group]
        axes[0].plot(xy[:, 0] * 1e3, xy[:, 1] * 1e3, color=colour, lw=1.2, label=group)
        if driving.any():
            axes[0].plot(*(xy[np.argmax(driving)] * 1e3), "o", color=colour, ms=4)
        axes[1].plot(s["time"], s["rover_travel"] * 1e3, color=colour, lw=1.2)
        axes[2].plot(s["time"][driving], s["rover_slip"][driving], color=colour, lw=1.0)
    axes[0].set_aspect("equal", adjustable="datalim")
    axes[0].set_xlabel("x [mm]")
    axes[0].set_ylabel("y [mm]")
    axes[0].set_title("path of the rover body (dot: drive start)")
    axes[1].set_xlabel("time [s]")
    axes[1].set_ylabel("travel since the drive started [mm]")
    axes[2].set_xlabel("time [s]")
    axes[2].set_ylabel("rover slip [-]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(_title(runs))
    fig.tight_layout()
    path = os.path.join(plot_dir, "trajectory.png")
    save_figure(fig, path, dpi)
    plt.close(fig)
    written.append(path)

    panels = [
        ("slip", "slip [-]", 1.0),
        ("sinkage", "rim sinkage [mm]", 1e3),
        ("driving_torque", "driving torque [N m]", 1.0),
        ("power", "drive power [W]", 1.0),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2))
    names = json.loads(runs[0][2]["attrs"].get("wheel_names", "[]"))
    for ax, (key, label, scale) in zip(axes, panels):
        for _, group, s in runs:
            driving = s["phase"] == PHASE_DRIVING
            values, time = s[key][driving] * scale, s["time"][driving]
            if len(runs) == 1:  # one run: every wheel
                for i in range(values.shape[1]):
                    ax.plot(time, values[:, i], lw=1.0, label=names[i] if i < len(names) else f"wheel {i}")
            else:  # many: the wheels' mean per run
                ax.plot(time, np.nanmean(values, axis=1), color=colours[group], lw=1.0, alpha=0.7, label=group)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        unique = dict(zip(labels, handles))
        ax.legend(unique.values(), unique.keys(), fontsize=7)
    fig.suptitle(_title(runs) + ("" if len(runs) == 1 else ": mean over the wheels"))
    fig.tight_layout()
    path = os.path.join(plot_dir, "wheels.png")
    save_figure(fig, path, dpi)
    plt.close(fig)
    written.append(path)
    return written


def _title(runs) -> str:
    if not runs:
        return ""
    attrs = runs[0][2]["attrs"]
    gravity = np.linalg.norm(np.asarray(attrs.get("gravity", [0, 0, 0]), dtype=float))
    return f"{attrs.get('name', '')}: |g| = {gravity:.3g} m/s^2, {len(runs)} run(s)"


def plot_scatter(out_dir: str, rows: list[dict], key: str, dpi: int = 120) -> str:
    """Mean, std and min-max of travel, slip and sinkage per group (a study's rows, cosim.study), over each
    group's steady runs (its `steady` count, in the title); a group with none is marked on every panel."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    x = np.arange(len(rows))
    steady = [r.get("steady") for r in rows]
    for ax, (name, label, scale) in zip(
        axes, [("travel", "travel [mm]", 1e3), ("slip", "slip [-]", 1.0), ("sinkage", "sinkage [mm]", 1e3)]
    ):
        mean = np.array([r.get(f"{name}_mean", np.nan) for r in rows]) * scale
        low = mean - np.array([r.get(f"{name}_min", np.nan) for r in rows]) * scale
        high = np.array([r.get(f"{name}_max", np.nan) for r in rows]) * scale - mean
        std = np.array([r.get(f"{name}_std", np.nan) for r in rows]) * scale
        ax.errorbar(x, mean, yerr=[low, high], fmt="o", capsize=6, label="min-max")
        ax.errorbar(x + 0.08, mean, yerr=std, fmt="s", capsize=3, label="std")
        ax.set_xticks(x, [str(r[key]) for r in rows])
        ax.set_xlim(-0.5, len(rows) - 0.5)
        for i in np.flatnonzero(~np.isfinite(mean)):  # no steady run: nothing to scatter there, said so
            ax.text(x[i], 0.5, "no steady run", transform=ax.get_xaxis_transform(), ha="center", color="C3")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    counts = ", ".join("?" if n is None else str(n) for n in steady)
    title = f"scatter over the steady replicas ({rows[0].get('replicas')} per {key}; steady: {counts})" if rows else ""
    fig.suptitle(title)
    fig.tight_layout()
    path = os.path.join(out_dir, PLOTS_DIR, "scatter.png")
    save_figure(fig, path, dpi)
    plt.close(fig)
    return path


def plot_slip_curve(out_dir: str, rows: list[dict], dpi: int = 120) -> str:
    """DP/W, driving torque and sinkage against slip with 95 % intervals (a slip study's rows); a row whose
    runs failed a validity check (its `validity` out of range) is circled by a hollow square."""
    plt = _pyplot()
    invalid = np.array([str(r.get("validity") or "").startswith("out of range") for r in rows], dtype=bool)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for ax, (name, label, scale) in zip(
        axes,
        [
            ("dp_over_w", "DP/W [-]", 1.0),
            ("driving_torque", "driving torque [N m]", 1.0),
            ("sinkage", "rim sinkage [mm]", 1e3),
        ],
    ):
        slip = np.array([r.get("slip_mean", r["slip_set"]) for r in rows])
        mean = np.array([r.get(f"{name}_mean", np.nan) for r in rows]) * scale
        ci = np.array([r.get(f"{name}_ci95", np.nan) for r in rows]) * scale
        ax.errorbar(slip, mean, yerr=np.nan_to_num(ci), fmt="o-", capsize=4)
        alone = ~np.isfinite(ci) & np.isfinite(mean)  # one steady replica: no interval, not an exact value
        if alone.any():
            ax.plot(slip[alone], mean[alone], "o", mfc="white", mec="C3", ms=9, label="one replica: no interval")
        outside = invalid & np.isfinite(mean)
        if outside.any():  # the scene was no valid test there (study.csv's validity names the checks)
            ax.plot(
                slip[outside], mean[outside], "s", mfc="none", mec="C1", mew=1.5, ms=13, label="out of range (validity)"
            )
        if alone.any() or outside.any():
            ax.legend(fontsize=8)
        ax.set_xlabel("slip [-]")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    fig.suptitle("drawbar pull / slip (error bars: 95 % interval over replicas)")
    fig.tight_layout()
    path = os.path.join(out_dir, PLOTS_DIR, "dbp_slip.png")
    save_figure(fig, path, dpi)
    plt.close(fig)
    return path


def plot_table(rows: list[dict], keys: list[str], units: dict[str, str] | None = None) -> str:
    """A plain-text table (studies print it); `units`: each column's unit, named in its header as the
    study's CSV names it ('slip [1]')."""
    names = [f"{k} [{units[k]}]" if units and k in units else k for k in keys]
    widths = [max(len(n), *(len(_fmt(r.get(k))) for r in rows)) for n, k in zip(names, keys)]
    lines = ["  ".join(n.ljust(w) for n, w in zip(names, widths)), "  ".join("-" * w for w in widths)]
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
