"""`cosim view RUN`: a picture of a run without ParaView, one frame per particle snapshot.

Each frame shows the grains from the side (seen along +y, the nearer grains drawn last) and in a
cut by the x-z plane through the first wheel's hub, its mid-plane when its axle lies along y as
on the testbed (the grains that the plane cuts, drawn at their cut radius, and the wheel's
outline in that plane: the rut), coloured by speed or by displacement
(from where each grain was first seen), with the wheels, the undisturbed surface, and the time,
phase, slip and sinkage in the corner. Rover runs and moving patches are followed: the view
is centred on the rover body.

Output by the suffix of `out`: .mp4 (ffmpeg: the one imageio-ffmpeg ships, else one on PATH),
.gif (Pillow), .png (one frame: the last, or `frame`), or a folder (one PNG per snapshot). It
draws with matplotlib's Agg backend: no display and no GPU needed. Every output is whole or absent: a
file is drawn under a temporary name and renamed, a folder of frames is drawn in FOLDER.drawing-* beside
it and then takes its place (a view stopped midway leaves the former frames as they were). Without
`overwrite`, an output that appeared while the view drew (another process's) is kept, and the view is
written beside it, as OUT-STEM.new.SUFFIX or OUT.new (FileExistsError naming both, as `cosim export`).

An `out` that is a symbolic link to a file is written through (the file replaced, the link kept) only
when that file's name ends in the picture's suffix and it is not the run's results.h5 or checkpoint; a
link to any other file (view.png -> results.h5) is refused before anything is drawn.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import shutil
import tempfile
from contextlib import contextmanager

import numpy as np

from soil.errors import ArgumentError, DamagedFileError, InputError
from soil.files import atomic_path, make_folders, output_target, remove_empty_folders

from .folders import CHECKPOINT_FILE, PLOTS_DIR, RESULTS_FILE
from .output import check_results, open_results
from .plots import save_figure
from .single_wheel import PHASE_DRIVING
from .snapshots import Displacements, Snapshot, read_snapshot, read_whole, snapshot_count

log = logging.getLogger(__name__)

COLOURS = ("speed", "displacement")
"""What the grains can be coloured by."""

MOVIE_SUFFIXES = (".mp4", ".gif")


class ViewError(InputError, ValueError):
    """`cosim view` cannot make a picture of what it was given (the message names the file or argument)."""


def ffmpeg_path() -> str | None:
    """The ffmpeg executable: imageio-ffmpeg's bundled one, else one on PATH, else None."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return shutil.which("ffmpeg")


def default_output(run_dir: str) -> str:
    """RUN/plots/view.mp4, or view.gif where there is no ffmpeg."""
    return os.path.join(run_dir, PLOTS_DIR, "view.mp4" if ffmpeg_path() else "view.gif")


def _output_kind(out: str) -> str:
    suffix = os.path.splitext(out)[1].lower()
    if suffix in MOVIE_SUFFIXES or suffix == ".png":
        return suffix
    if suffix == "" or out.endswith(os.sep) or os.path.isdir(out):
        return "frames"
    raise ViewError(f"--out {out!r}: unknown suffix {suffix!r} (use .mp4, .gif, .png or a folder for PNG frames)")


def _results(run_dir: str) -> str:
    path = os.path.join(run_dir, RESULTS_FILE) if os.path.isdir(run_dir) else run_dir
    if not os.path.isfile(path):
        raise ViewError(f"{run_dir!r} is not a run folder: no {RESULTS_FILE} in it")
    return path


class _Scene:
    """What every frame shares: the run's attributes, the mesh, the colour range and the view box."""

    def __init__(self, f, colour: str):
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        self.name = str(attrs.get("name", "run"))
        self.gravity = float(np.linalg.norm(np.asarray(attrs.get("gravity", [0, 0, 0]), dtype=float)))
        self.surface = float(attrs.get("surface_height", np.nan))
        self.rover = attrs.get("kind") == "rover"
        self.follow = self.rover or f["particles"].attrs.get("layout") == "ragged"
        self.colour = colour
        slip = "rover/slip" if self.rover else "wheels/slip"
        names = ("wheels/mesh/triangles", "wheels/mesh/wheel", "wheels/time", "wheels/phase", slip, "wheels/sinkage")
        missing = [name for name in names if name not in f]
        if missing:
            raise DamagedFileError(f"{f.filename}: the results file is damaged (missing {', '.join(missing)})")
        self.triangles = read_whole(f, "wheels/mesh/triangles")
        self.vertex_wheel = read_whole(f, "wheels/mesh/wheel")
        self.step_time = read_whole(f, "wheels/time")
        self.phase = read_whole(f, "wheels/phase")
        self.slip = read_whole(f, slip)
        self.slip = self.slip if self.slip.ndim == 1 else self.slip[:, 0]
        self.sinkage = read_whole(f, "wheels/sinkage")[:, 0] if len(self.step_time) else np.zeros(0)
        count = snapshot_count(f)
        if count == 0 or not len(read_snapshot(f, 0).ids):
            raise ArgumentError(
                f"{f.filename}: no grains to draw (a run on SCM or the analytic terrain, or one without snapshots): "
                "`cosim view` draws the grains; `cosim plot RUN` draws the run's series"
            )
        # one pass for the colour range: the largest per-snapshot 99th percentile (a few fast grains do not wash
        # it out) over the drive (the landing's impact would), or over every snapshot without a drive
        displacements = Displacements()
        peaks, driving = [], []
        for k in range(count):
            s = read_snapshot(f, k)
            peaks.append(np.percentile(self.values(s, displacements), 99) if len(s.ids) else 0.0)
            row = self.step(s.time)
            driving.append(row >= 0 and self.phase[row] == PHASE_DRIVING)
        peaks_arr = np.asarray(peaks)[driving] if any(driving) else np.asarray(peaks)
        self.vmax = max(float(np.max(peaks_arr)), 1e-9)
        first = read_snapshot(f, 0)
        wheels = read_whole(f, "particles/wheel_vertices")
        low = np.min(first.position - first.radius[:, None], axis=0)
        high = np.max(first.position + first.radius[:, None], axis=0)
        self.z_range = (low[2], max(high[2], float(np.nanmax(wheels[..., 2]))))
        self.x_range = (min(low[0], float(np.nanmin(wheels[..., 0]))), max(high[0], float(np.nanmax(wheels[..., 0]))))
        self.half_width = (high[0] - low[0]) / 2

    def values(self, s: Snapshot, displacements: Displacements) -> np.ndarray:
        """Speed or displacement magnitude of each grain [mm/s or mm]."""
        if self.colour == "speed":
            return np.linalg.norm(np.asarray(s.velocity, dtype=np.float64), axis=1) * 1e3
        return np.linalg.norm(displacements.of(s), axis=1) * 1e3

    def step(self, time: float) -> int:
        """The last macro step at or before `time` (-1: none yet)."""
        return int(np.searchsorted(self.step_time, time + 1e-9)) - 1


class _Frame:
    """The figure: two panels, the colour bar and the labels made once (the layout is computed for the
    first frame and then kept: laying out every frame would cost more than drawing it); `draw` puts one
    snapshot's grains, wheels and corner text in."""

    COLOUR_MAP = "viridis"

    def __init__(self, fig, scene: _Scene):
        from matplotlib import cm, colors

        self.fig, self.scene = fig, scene
        self.side, self.cut = fig.subplots(2, 1, sharex=True)
        for ax in (self.side, self.cut):
            if np.isfinite(scene.surface):
                ax.axhline(scene.surface * 1e3, color="0.3", ls="--", lw=0.8)
            ax.set_xlim(scene.x_range[0] * 1e3, scene.x_range[1] * 1e3)
            ax.set_ylim(scene.z_range[0] * 1e3, scene.z_range[1] * 1e3 + 2)
            ax.set_aspect("equal")
            ax.set_ylabel("z [mm]")
        self.side.set_title("side view", fontsize=9, loc="left")
        self.cut.set_xlabel("x [mm]")
        mappable = cm.ScalarMappable(norm=colors.Normalize(0.0, scene.vmax), cmap=self.COLOUR_MAP)
        label = "grain speed [mm/s]" if scene.colour == "speed" else "grain displacement [mm]"
        fig.colorbar(mappable, ax=[self.side, self.cut], label=label, shrink=0.8, extend="max")
        fig.suptitle(f"{scene.name}: |g| = {scene.gravity:.3g} m/s^2, dashed: undisturbed surface", fontsize=10)
        self.corner = self.side.text(
            0.01,
            0.97,
            "",
            transform=self.side.transAxes,
            va="top",
            fontsize=9,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
        self.artists: list = []
        self.laid_out = False

    def _grains(self, ax, centres, radii, values) -> None:
        from matplotlib.collections import EllipseCollection

        collection = EllipseCollection(
            2 * radii * 1e3,
            2 * radii * 1e3,
            np.zeros(len(radii)),
            units="xy",
            offsets=centres * 1e3,
            offset_transform=ax.transData,
            array=values,
            cmap=self.COLOUR_MAP,
            clim=(0.0, self.scene.vmax),
            linewidths=0,
        )
        self.artists.append(ax.add_collection(collection))

    def draw(self, s: Snapshot, values: np.ndarray) -> None:
        from matplotlib.collections import LineCollection, PolyCollection

        scene, side, cut = self.scene, self.side, self.cut
        for artist in self.artists:
            artist.remove()
        self.artists = []
        hub = s.wheel_vertices[scene.vertex_wheel == 0].mean(axis=0)
        if scene.follow and np.all(np.isfinite(s.rover_position)):
            centre = s.rover_position[0]
            side.set_xlim((centre - scene.half_width) * 1e3, (centre + scene.half_width) * 1e3)
        # side view, looking along +y: the grains behind the wheel's mid-plane, the wheels, then those in front
        order = np.argsort(-s.position[:, 1])
        behind = order[s.position[order, 1] >= hub[1]]
        front = order[s.position[order, 1] < hub[1]]
        self._grains(side, s.position[behind][:, [0, 2]], s.radius[behind], values[behind])
        wheel_faces = s.wheel_vertices[scene.triangles][:, :, [0, 2]] * 1e3
        self.artists.append(side.add_collection(PolyCollection(list(wheel_faces), facecolors="0.7", edgecolors="none")))
        self._grains(side, s.position[front][:, [0, 2]], s.radius[front], values[front])
        # the cut: the grains the plane y = hub y passes through, at their cut radius, and the wheel's outline in it
        dy = s.position[:, 1] - hub[1]
        inside = np.abs(dy) < s.radius
        cut_radius = np.sqrt(np.maximum(s.radius[inside] ** 2 - dy[inside] ** 2, 0.0))
        self._grains(cut, s.position[inside][:, [0, 2]], cut_radius, values[inside])
        segments = _plane_section(s.wheel_vertices, scene.triangles, hub[1])
        if len(segments):
            lines = LineCollection(list(segments[:, :, [0, 2]] * 1e3), colors="k", linewidths=1.2)
            self.artists.append(cut.add_collection(lines))
        cut.set_title(f"cut through the wheel's mid-plane (y = {hub[1] * 1e3:.1f} mm)", fontsize=9, loc="left")
        row = scene.step(s.time)
        corner = [f"t = {s.time:.3g} s"]
        if row >= 0:
            driving = scene.phase[row] == PHASE_DRIVING
            corner.append("driving" if driving else "landing")
            if driving and np.isfinite(scene.slip[row]):
                corner.append(f"slip {scene.slip[row]:.2f}")
            if np.isfinite(scene.sinkage[row]):
                corner.append(f"sinkage {scene.sinkage[row] * 1e3:.1f} mm")
        self.corner.set_text(", ".join(corner))
        if not self.laid_out:
            self.fig.canvas.draw()  # the constrained layout, once
            self.fig.set_layout_engine("none")
            self.laid_out = True


def _plane_section(vertices: np.ndarray, triangles: np.ndarray, y: float) -> np.ndarray:
    """(M, 2, 3) segments where the plane at height y along the y axis cuts a triangle mesh."""
    corners = vertices[triangles]  # (F, 3, 3)
    side = corners[:, :, 1] - y
    segments = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        crossing = (side[:, a] * side[:, b]) < 0
        fraction = side[:, a] / np.where(crossing, side[:, a] - side[:, b], 1.0)
        points = corners[:, a] + fraction[:, None] * (corners[:, b] - corners[:, a])
        segments.append(np.where(crossing[:, None], points, np.nan))
    stacked = np.stack(segments, axis=1)  # (F, 3 edges, 3)
    two = np.sum(np.isfinite(stacked[:, :, 0]), axis=1) == 2
    picked = [row[np.isfinite(row[:, 0])] for row in stacked[two]]
    return np.array(picked).reshape(-1, 2, 3) if picked else np.zeros((0, 2, 3))


FPS_RANGE = (1, 120)
"""Movie frames per second a view takes [1/s]: players handle these."""
DPI_RANGE = (10, 600)
"""Pixels per inch of a 10 inch wide frame [-]: up to 6000 pixels wide (a frame of about 0.3 GB in memory)."""
FRAME_NAME = re.compile(r"frame_\d{4,}\.png|tmp\w+\.png")
"""The name of one PNG of a folder of frames (or of one a killed view left half-written: soil.files.atomic_path)."""


def render(
    run_dir: str,
    out: str | None = None,
    colour: str = "speed",
    fps: int = 5,
    dpi: int = 100,
    frame: int | None = None,
    overwrite: bool = False,
) -> str:
    """Write the picture of a run (module docstring); returns the path written. An `out` that exists is
    replaced only with `overwrite` (the run's own default picture is made again), also one that appeared
    while the view drew (kept; the view written beside it: FileExistsError naming both); a file is written
    whole or not at all (under a temporary name, then renamed); a link to the run's results.h5 or to a
    file of another suffix is refused (ViewError)."""
    if colour not in COLOURS:
        raise ViewError(f"--color {colour!r}: choose one of {', '.join(COLOURS)}")
    for option, value, (low, high) in (("--fps", fps, FPS_RANGE), ("--dpi", dpi, DPI_RANGE)):
        if isinstance(value, bool) or not low <= value <= high:
            raise ViewError(f"{option} {value}: allowed {low} to {high}")
    path = _results(run_dir)
    own = default_output(os.path.dirname(os.path.abspath(path)))
    out = out or own
    kind = _output_kind(out)
    if frame is not None and kind != ".png":  # a movie or a folder of frames draws every snapshot
        raise ViewError(f"--frame {frame}: picks the snapshot of a .png picture; --out {out!r} draws every one")
    replace = overwrite or os.path.abspath(out) == own
    inputs = (path, os.path.join(os.path.dirname(os.path.abspath(path)), CHECKPOINT_FILE))
    _free_output(out, kind, replace, inputs)
    # damage named before anything is drawn; every output is written whole at the end, so the grains'
    # datasets are left to read_snapshot (everything else is read through)
    check_results(path, data=False)
    with open_results(path) as f:
        count = snapshot_count(f)
        if count == 0:
            raise ViewError(
                f"{path} holds no particle snapshots (output.snapshot_interval, or a run that stopped early)"
            )
        if frame is not None and not -count <= frame < count:
            raise ViewError(f"--frame {frame}: {path} holds snapshots 0 .. {count - 1}")
        scene = _Scene(f, colour)
        from .plots import _pyplot

        plt = _pyplot()
        width = scene.half_width * 2 if scene.follow else scene.x_range[1] - scene.x_range[0]
        aspect = (scene.z_range[1] - scene.z_range[0] + 2e-3) / max(width, 1e-9)
        fig = plt.figure(figsize=(10, float(np.clip(2 * 8.3 * aspect + 1.4, 3.0, 14.0))), layout="constrained")
        view = _Frame(fig, scene)
        displacements = Displacements()
        writer = _movie_writer(kind, out, fps) if kind in MOVIE_SUFFIXES else None
        # a picture's or movie's folder is made by atomic_path, a folder of frames' by _whole_folder (each
        # removed again when the view fails)
        try:
            if kind == ".png":
                chosen = (frame if frame is not None else -1) % count
                for k in range(chosen + 1):  # the displacements need the snapshots before it
                    s = read_snapshot(f, k)
                    values = scene.values(s, displacements)
                view.draw(s, values)
                save_figure(fig, out, dpi, replace=replace)
            elif kind == "frames":  # a shorter run's view keeps none of a longer one's last frames
                with _whole_folder(out, replace) as drawing:
                    for k in range(count):
                        s = read_snapshot(f, k)
                        view.draw(s, scene.values(s, displacements))
                        save_figure(fig, os.path.join(drawing, f"frame_{k:04d}.png"), dpi)
            else:
                assert writer is not None  # a movie's kind
                with atomic_path(out, suffix=kind, replace=replace) as partial, writer.saving(fig, partial, dpi):
                    for k in range(count):
                        s = read_snapshot(f, k)
                        view.draw(s, scene.values(s, displacements))
                        writer.grab_frame()
        finally:
            plt.close(fig)
    return out


@contextmanager
def _whole_folder(out: str, replace: bool = True):
    """Yield a new folder beside `out` (OUT.drawing-*) to draw a set of frames into; on success it takes
    `out`'s place (the former folder moved aside first, then its frames removed), on any error it is
    removed and `out` is left as it was (a view killed midway leaves the former set whole, and at most its
    OUT.drawing-* folder beside it; killed in the instant between the two renames, the former set is
    whole in OUT.former-*). `out` a link to a folder: that folder is replaced, the link stays.

    replace False: `out` must still be absent or an empty folder when the frames are done; a file or a
    folder of files that appeared there meanwhile (another process's) is left as it is and the frames are
    kept beside it as OUT.new (OUT.new-2, ...): FileExistsError naming both."""
    target = os.path.realpath(out)
    parent, name = os.path.split(target)
    made = make_folders(parent)
    drawing = former = None
    try:
        try:
            drawing = tempfile.mkdtemp(prefix=f"{name}.drawing-", dir=parent)
        except OSError as error:
            raise OSError(
                error.errno, f"the frames are drawn beside it first, and its folder {parent} refuses a new one", out
            ) from error
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(drawing, 0o777 & ~mask)  # a normally made folder's permissions (mkdtemp's 0700 would hide it)
        yield drawing
        if not replace:  # onto nothing or an empty folder only: the rename refuses anything else
            _place_new_folder(drawing, target, out)
            return
        if os.path.lexists(target):  # moved aside, not removed first: no moment without a whole set
            former = tempfile.mkdtemp(prefix=f"{name}.former-", dir=parent)
            os.rename(target, former)  # onto an empty folder: allowed
        os.rename(drawing, target)
    except BaseException:
        if former is not None and not os.path.lexists(target):  # stopped between the two renames
            os.rename(former, target)
        elif former is not None and os.path.isdir(former) and not os.listdir(former):  # the first one failed
            os.rmdir(former)
        if drawing is not None:
            shutil.rmtree(drawing, ignore_errors=True)
        remove_empty_folders(made)
        raise
    if former is not None:  # the former frames; a file put there while the view drew is kept, and said
        for entry in os.listdir(former):
            if FRAME_NAME.fullmatch(entry):
                os.remove(os.path.join(former, entry))
        try:
            os.rmdir(former)
        except OSError:
            log.warning("%s: files put there while the view drew were kept in %s", out, former)


FOLDER_TAKEN = {errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR}
"""The errors of os.rename(folder, name) where a file or a folder of files is at name."""


def _place_new_folder(drawing: str, target: str, out: str) -> None:
    """Rename the finished folder `drawing` to `target` where that is absent or an empty folder (os.rename
    refuses anything else, atomically); else to TARGET.new[-k] beside it (a folder's name has no suffix:
    frames.v2 gives frames.v2.new), and raise FileExistsError naming `out` and that folder."""
    try:
        os.rename(drawing, target)
        return
    except OSError as error:
        if error.errno not in FOLDER_TAKEN:
            raise
    for k in range(1, 10**6):
        kept = f"{target}.new{'' if k == 1 else f'-{k}'}"
        if os.path.lexists(kept):
            continue
        try:
            os.rename(drawing, kept)
        except OSError as error:  # taken meanwhile
            if error.errno in FOLDER_TAKEN:
                continue
            raise
        raise FileExistsError(
            errno.EEXIST,
            f"appeared while the frames were drawn (another process wrote it) and was left as it is; the frames "
            f"are in {kept}",
            out,
        )
    raise FileExistsError(errno.EEXIST, f"appeared while the frames were drawn; they are in {drawing}", out)


def _free_output(out: str, kind: str, replace: bool, inputs=()) -> None:
    """Refuse an `out` that view must not write (before anything is drawn): a folder where a file goes, a
    file where a folder of frames goes (also written `picture.png/`), a folder that holds other files than
    frames, a link that leads to one of `inputs` (the run's results.h5 and checkpoint) or to a file whose
    name does not end in the picture's suffix (soil.files.output_target: such a link is never written
    through), and without `replace` one that exists (OutputExistsError)."""
    from .folders import OutputExistsError

    if kind != "frames":
        try:
            output_target(out, (kind,), inputs)
        except ArgumentError as error:
            raise ViewError(str(error)) from None
    if not os.path.lexists(out.rstrip(os.sep) or out):  # lexists('picture.png/') is False for a file
        return
    if kind != "frames":
        if os.path.isdir(out):
            raise ViewError(f"--out {out!r} is a folder; a {kind} picture is a file: give a file name")
        if not replace:
            raise OutputExistsError(f"--out {out!r} exists; pass --overwrite to replace it")
        return
    if not os.path.isdir(out):
        raise ViewError(f"--out {out!r} is a file; frames go into a folder: give a new or empty folder")
    here, target = os.path.realpath(os.getcwd()), os.path.realpath(out)
    if os.path.commonpath([here, target]) == target:  # the set takes the folder's place: not the one we stand in
        raise ViewError(f"--out {out!r} is the working folder or holds it; give a folder of frames of its own")
    names = sorted(os.listdir(out))
    foreign = [n for n in names if not FRAME_NAME.fullmatch(n)]
    if foreign:
        raise ViewError(
            f"--out {out!r} holds files that are not a view's frames ({', '.join(foreign[:4])}"
            f"{', ...' if len(foreign) > 4 else ''}): give a new or empty folder"
        )
    if names and not replace:
        raise OutputExistsError(f"--out {out!r} holds {len(names)} frames; pass --overwrite to replace them")


def _movie_writer(kind: str, out: str, fps: int):
    import logging

    from matplotlib import animation, rcParams

    logging.getLogger("matplotlib.animation").setLevel(logging.WARNING)  # not the ffmpeg command line

    if kind == ".gif":
        return animation.PillowWriter(fps=fps)
    ffmpeg = ffmpeg_path()
    if ffmpeg is None:
        raise ViewError(
            f"--out {out!r}: an .mp4 needs ffmpeg (pip install imageio-ffmpeg); or write a .gif or a folder of PNGs"
        )
    rcParams["animation.ffmpeg_path"] = ffmpeg
    # yuv420p plays everywhere; it needs even frame sizes, which the scale filter guarantees
    return animation.FFMpegWriter(
        fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p", "-vf", "scale=trunc(iw/2)*2:trunc(ih/2)*2"]
    )


def summary_line(path: str) -> str:
    """What `cosim view` prints: the file and its size."""
    if os.path.isdir(path):
        names = sorted(os.listdir(path))
        return f"{path}: {len(names)} frames"
    return f"{path}: {os.path.getsize(path) / 1024:.0f} kB"


__all__ = ["COLOURS", "ViewError", "default_output", "ffmpeg_path", "render", "summary_line"]
