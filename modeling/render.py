"""Offscreen PNG of a heart model, like Fig. 5 of Wood et al. 2018.

Two views of the patient frame side by side: coronal (seen from the front,
patient's left on the picture's right) and sagittal (seen from the patient's
left). The mesh is drawn semi-opaque, the slab ellipses as yellow lines, the
heart frame's x, y, z as red, green, blue arrows, the fiducials as grey
spheres.  Each view is drawn in parallel projection by matplotlib alone
(:func:`modeling.projection.project_panel`: no OpenGL, a fraction of VTK's
memory and time), cut to what it shows and laid out (:func:`compose_figure`)
with titles, a legend for every colour and marker, and a scale bar per view.

The registration's 3-D view (:mod:`registration.view`) is drawn the same way.
:func:`render_panel` draws a panel with pyvista instead, for a caller who
wants VTK's rendering; it needs offscreen OpenGL: VTK picks its window from
``VTK_DEFAULT_OPENGL_WINDOW`` (``vtkOSOpenGLRenderWindow`` needs Debian's ``libosmesa6``;
``vtkEGLRenderWindow`` needs ``libegl1 libgl1``); without the variable and
without an X display, VTK 9.4+ falls back to EGL. Because a missing GL stack
can abort the process inside VTK, :func:`offscreen_available` first probes it
in a subprocess; when it fails :func:`render_png` raises
:class:`RenderError` and the caller skips the picture.
"""

from __future__ import annotations

import atexit
import functools
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from hrcore.figlayout import fixed_margins, subplots
from imaging.files import atomic_path
from modeling.mesh import MeshError
from modeling.model import HeartModel
from modeling.surface import decimate

__all__ = [
    "RenderError", "compose_figure", "offscreen_available", "render_model_pictures", "render_model_png", "render_panel",
    "render_png", "start_offscreen_probe",
]


def _choose_offscreen_window() -> None:
    """Without a display, point VTK at an offscreen OpenGL (OSMesa, else EGL)
    unless the user chose one, so it does not try (and warn about) X first."""
    if os.environ.get("DISPLAY") or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return
    import ctypes.util

    if ctypes.util.find_library("OSMesa"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"
    elif ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"


_choose_offscreen_window()

_PROBE = (
    "import pyvista as pv\n"
    "pv.OFF_SCREEN = True\n"
    "p = pv.Plotter(off_screen=True, window_size=(64, 48))\n"
    "p.add_mesh(pv.Sphere())\n"
    "img = p.screenshot(return_img=True)\n"
    "p.close()\n"
    "print('ok' if img.std() > 1 else 'blank')\n"
)


class RenderError(HeartregError, RuntimeError):
    """No offscreen OpenGL, or VTK failed to draw: skip the picture."""


_probe: subprocess.Popen | None = None


def start_offscreen_probe() -> None:
    """Start probing offscreen OpenGL in a subprocess, in the background.

    A command that will draw calls this first: the probe (a fresh interpreter
    importing pyvista and drawing a sphere, a second or two) then runs beside the
    command's own work, and :func:`offscreen_available` only collects its answer.
    """
    global _probe
    if _probe is not None or offscreen_available.cache_info().currsize:
        return
    try:
        _probe = subprocess.Popen(
            [sys.executable, "-c", _PROBE], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL, text=True, env=os.environ.copy(),
        )
    except OSError:
        return
    atexit.register(_stop_probe)


def _stop_probe() -> None:
    if _probe is not None and _probe.poll() is None:
        _probe.kill()
        _probe.wait()


@functools.lru_cache(maxsize=1)
def offscreen_available(timeout_s: float = 60.0) -> bool:
    """Whether pyvista can draw offscreen here (probed once, in a subprocess,
    started by :func:`start_offscreen_probe` or now).

    Examples
    --------
    >>> from modeling import offscreen_available
    >>> offscreen_available() in (True, False)  # doctest: +SKIP
    True
    """
    if _probe is None:
        start_offscreen_probe()
    if _probe is None:
        return False
    try:
        out, _ = _probe.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _stop_probe()
        return False
    if _probe.returncode in (-signal.SIGINT, -signal.SIGTERM):
        # Ctrl-C or a SIGTERM reached the probe too: stop, do not report "no OpenGL" and exit 0
        raise KeyboardInterrupt
    return _probe.returncode == 0 and out.strip().endswith("ok")


def render_model_png(
    model: HeartModel,
    path,
    *,
    ellipses: bool = True,
    size: tuple[int, int] = (1300, 760),
) -> Path:
    """Draw the model in the patient frame to a PNG (written atomically).

    Parameters
    ----------
    model : HeartModel
    path : str or Path
        Output ``.png``.
    ellipses : bool
        Draw the slab ellipses of the frame fit.
    size : (width, height) int, pixels

    Raises
    ------
    RenderError
        The drawing failed or came out blank.

    Examples
    --------
    A second or so, hence skipped:

    >>> import tempfile
    >>> import numpy as np
    >>> from modeling import make_heart_model, mask_to_mesh, render_model_png
    >>> k, j, i = np.mgrid[:50, :40, :40]
    >>> mask = ((k - 25) / 22) ** 2 + ((j - 20) / 14) ** 2 + ((i - 20) / 12) ** 2 < 1
    >>> mesh = mask_to_mesh(mask, np.diag([2.0, 2.0, 2.0, 1.0]), target_faces=2000)
    >>> model = make_heart_model(mesh, cardiac_phase=0.7, cardiac_phase_source="example", base_hint=[0, 0, 1])
    >>> render_model_png(model, tempfile.mkdtemp() + "/model.png").suffix  # doctest: +SKIP
    '.png'
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    return render_png(lambda size: _draw(model, ellipses=ellipses, size=size), path, size=size, what="the model",
                      opengl=False)


def render_model_pictures(model: HeartModel, panels, folder) -> tuple[Path, Path]:
    """A model's two pictures in ``folder``: ``model.png`` and ``model_ct.png``, drawn at once.

    ``model.png`` is :func:`render_model_png`; ``model_ct.png`` is
    :func:`modeling.ct_overlay.render_ct_png` of ``panels``
    (:func:`modeling.ct_overlay.ct_panels`, cut from the CT before it is
    freed).  The second is drawn on a thread beside the first: each draws
    its own ``Figure`` on Agg (no pyplot state; matplotlib keeps its fonts
    per thread), and Agg's rasteriser, the image resampling and the PNG
    compression release the GIL, so on two cores both take about the time of
    the longer (0.7 s instead of 0.95 s for a 20k-face model of a 512 x 512
    x 288 CT), each picture byte for byte what it is drawn alone.

    Returns
    -------
    (model_png, model_ct_png) : Path, Path

    Raises
    ------
    RenderError
        ``model.png`` could not be drawn (once the other is done).
    """
    from concurrent.futures import ThreadPoolExecutor

    from modeling.ct_overlay import render_ct_png

    folder = Path(folder)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="model_ct") as pool:
        ct = pool.submit(render_ct_png, panels, folder / "model_ct.png")
        picture = render_model_png(model, folder / "model.png")
        return picture, ct.result()


def render_png(draw, path, *, size: tuple[int, int], what: str, opengl: bool = True) -> Path:
    """Run an offscreen drawing and save its image as a PNG, atomically.

    Parameters
    ----------
    draw : callable
        ``draw((width, height)) -> (h, w, 3) uint8`` image, using pyvista offscreen.
    path : str or Path
        Output ``.png``.
    size : (width, height) int, pixels
    what : str
        What is drawn, for error messages.
    opengl : bool
        Whether ``draw`` needs offscreen OpenGL (checked first).

    Raises
    ------
    RenderError
        No offscreen OpenGL (the message says what to install), VTK failed, or
        the image came out blank.
    """
    width, height = (int(s) for s in size)
    if width < 64 or height < 64:
        raise ValueError(f"size must be at least (64, 64) pixels, got {size}")
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"path must end in .png, got {path.name}")
    if opengl and not offscreen_available():
        raise RenderError(
            "offscreen OpenGL is not available: install Debian's libosmesa6 (and set "
            "VTK_DEFAULT_OPENGL_WINDOW=vtkOSOpenGLRenderWindow) or libegl1 libgl1 "
            "(vtkEGLRenderWindow); skipping the 3-D picture"
        )
    try:
        img = draw((width, height))
    except RenderError:
        raise
    except Exception as exc:  # noqa: BLE001 - VTK raises many kinds
        raise RenderError(f"VTK failed to render {what}: {exc}") from exc
    if img.std() < 1.0:
        raise RenderError("the rendered image is blank; check the offscreen OpenGL setup")
    from PIL import Image

    from hrcore.figlayout import PNG_OPTIONS

    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG", **PNG_OPTIONS)
    return path


#: colours of the model picture, shared with its legend.
MESH_COLOUR = "#d46a6a"
ELLIPSE_COLOUR = "#e0b000"
FIDUCIAL_COLOUR = "#505050"
AXIS_COLOURS = ("#d62728", "#2ca02c", "#1f4fd6")
#: The picture draws the surface with at most this many faces: at its scale (~4 px/mm) a
#: 20k-face model decimated to 8k looks the same (mean pixel difference 1.7 of 255) and
#: draws in half the time.
PICTURE_FACES = 8000


def render_panel(add_actors, *, size, towards_camera, up, focus, extent_mm) -> tuple[np.ndarray, float]:
    """One offscreen pyvista view in parallel projection, and its scale.

    Parameters
    ----------
    add_actors : callable
        ``add_actors(plotter)`` adds the meshes.
    size : (width, height) int, pixels
    towards_camera, up : (3,) float
        Direction from ``focus`` to the camera, and the picture's up.
    focus : (3,) float, mm
    extent_mm : float
        Size of the scene (sets the camera distance).

    Returns
    -------
    image : (h, w, 3) uint8
    px_per_mm : float
        Pixels per millimetre in the picture (parallel projection: the same everywhere).
    """
    import pyvista as pv

    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=tuple(int(v) for v in size), border=False)
    try:
        plotter.set_background("white")
        add_actors(plotter)
        plotter.enable_parallel_projection()
        focus = np.asarray(focus, dtype=float)
        camera = focus + np.asarray(towards_camera, dtype=float) * 4.0 * extent_mm
        plotter.camera_position = [tuple(camera), tuple(focus), tuple(up)]
        plotter.reset_camera()
        img = np.asarray(plotter.screenshot(return_img=True))[..., :3]
        px_per_mm = (size[1] / 2.0) / plotter.camera.parallel_scale
    finally:
        plotter.close()
    return img, float(px_per_mm)


def _crop(img: np.ndarray, margin: int = 10) -> np.ndarray:
    """The picture cut to what is drawn on it (non-white), with a margin."""
    ink = np.any(img < 245, axis=2)
    if not ink.any():
        return img
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, img.shape[0])
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, img.shape[1])
    return img[r0:r1, c0:c1]


def _scale_length_mm(px_per_mm: float, width_px: int) -> float:
    """A round length whose bar is about a fifth of the panel's width."""
    target = 0.2 * width_px / px_per_mm
    for mm in (1, 2, 5, 10, 20, 25, 50, 100, 200):
        if mm >= 0.6 * target:
            return float(mm)
    return 200.0


def compose_figure(panels, *, size, titles, handles, suptitle, orientation=None, colorbar=None) -> np.ndarray:
    """Panels side by side with titles, a scale bar each, one legend and a colour bar.

    Parameters
    ----------
    panels : list of (image, px_per_mm)
        From :func:`render_panel`; each is cut to its content.
    size : (width, height) int, pixels of the result
    titles : list of str
    handles : list of matplotlib artists
        Legend entries (one per colour and marker drawn).
    suptitle : str
    orientation : list of (str, str), optional
        Per panel, the picture's right and up directions in words.
    colorbar : (cmap, vmin, vmax, label), optional

    Returns
    -------
    (height, width, 3) uint8
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    width, height = size
    dpi = 100
    pt = min(1.0, width / 1250.0)  # text shrinks with a small picture, never grows
    # as many columns as the longest label allows (about 7 px per character at 12 pt)
    longest = max(len(h.get_label()) for h in handles)
    ncol = max(1, min(len(handles), 3, int(width / (7.2 * pt * longest + 70))))
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    axes = subplots(fig, 1, len(panels), squeeze=False)[0]
    # fixed room (inches, text at the scale pt plus matplotlib's unscaled pads): the
    # suptitle (at 98 % of the height) and titles above; the legend's rows and the
    # orientation labels below; a colorbar takes its own share of the panels' room
    rows = -(-len(handles) // ncol)
    fixed_margins(fig, left_in=0.35 * pt, right_in=0.1 * pt, bottom_in=(0.35 + 0.27 * rows) * pt + 0.05,
                  top_in=0.45 * pt + 0.02 * height / dpi + 0.09, wspace_in=0.45 * pt)
    for k, (ax, (img, px_per_mm), title) in enumerate(zip(axes, panels, titles)):
        img = _crop(img)
        band = np.full((max(int(0.1 * img.shape[0]), 24), img.shape[1], 3), 255, dtype=img.dtype)
        img = np.concatenate([img, band])  # white room under the drawing for the scale bar
        ax.imshow(img, interpolation="antialiased")
        ax.set_title(title, fontsize=13 * pt)
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
        if orientation is not None:
            right, up = orientation[k]
            ax.set_xlabel(f"{right} \u2192", fontsize=11 * pt, loc="right")
            ax.set_ylabel(f"{up} \u2192", fontsize=11 * pt, loc="top")
        mm = _scale_length_mm(px_per_mm, img.shape[1])
        ax.add_artist(AnchoredSizeBar(
            ax.transData, mm * px_per_mm, f"{mm:g} mm", "lower left", pad=0.3, frameon=False,
            size_vertical=max(2.0, 0.006 * img.shape[0]), fontproperties=FontProperties(size=12 * pt),
        ))
    if colorbar is not None:
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        cmap, vmin, vmax, label = colorbar
        bar = fig.colorbar(ScalarMappable(Normalize(vmin, vmax), cmap), ax=list(axes), shrink=0.75, pad=0.01,
                           fraction=0.08)  # the bar and its labels, not more
        bar.set_label(label, fontsize=12 * pt)
        bar.ax.tick_params(labelsize=11 * pt)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=12 * pt, frameon=False)
    fig.suptitle(suptitle, fontsize=14 * pt)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _draw(model: HeartModel, *, ellipses: bool, size) -> np.ndarray:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from modeling.projection import Scene, project_panel

    mesh = model.mesh_patient()
    if mesh.n_faces > PICTURE_FACES:
        try:
            mesh = decimate(mesh, PICTURE_FACES)
        except MeshError:
            pass  # drawn as it is
    frame = model.frame
    origin = frame.origin_patient_mm
    axes = frame.axes_patient
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    arrow_mm = 0.75 * extent
    fid = model.fiducials_patient_mm
    phase = "unknown" if model.cardiac_phase is None else f"{model.cardiac_phase:.2f}"

    scene = Scene(surfaces=[(mesh.vertices, mesh.faces, MESH_COLOUR, 0.55)])
    if ellipses:
        for e in frame.ellipses:
            ring = e.points(96)
            scene.lines.append((np.vstack([ring, ring[:1]]), ELLIPSE_COLOUR, 3))
            scene.balls.append((e.centre_mm, 1.2, ELLIPSE_COLOUR))
    for axis, colour in zip(axes.T, AXIS_COLOURS):  # as pyvista's Arrow(tip_length=0.12, tip_radius=0.04, ...)
        scene.arrows.append((origin, arrow_mm * axis, colour, 0.015 * arrow_mm, 0.04 * arrow_mm, 0.12 * arrow_mm))
    for f in fid:
        scene.balls.append((f, 2.5, FIDUCIAL_COLOUR))

    points = np.vstack([mesh.vertices, fid]) if len(fid) else mesh.vertices
    focus = 0.5 * (points.min(axis=0) + points.max(axis=0))
    panel = (max(size[0] // 2, 64), max(size[1], 64))  # each view at about the size it is shown, then cut
    views = [
        ("coronal, seen from anterior", (0.0, -1.0, 0.0), ("patient's left", "superior")),
        ("sagittal, seen from the patient's left", (1.0, 0.0, 0.0), ("posterior", "superior")),
    ]
    panels = [project_panel(scene, size=panel, towards_camera=towards, up=(0.0, 0.0, 1.0), focus=focus)
              for _, towards, _ in views]
    handles = [
        Patch(facecolor=MESH_COLOUR, alpha=0.6, edgecolor="none", label="epicardial surface (heart model)"),
        Line2D([], [], color=AXIS_COLOURS[0], lw=3, label="heart x (anterior)"),
        Line2D([], [], color=AXIS_COLOURS[1], lw=3, label="heart y = z \u00d7 x"),
        Line2D([], [], color=AXIS_COLOURS[2], lw=3, label="heart z (apex \u2192 base)"),
    ]
    if ellipses:
        handles.insert(1, Line2D([], [], color=ELLIPSE_COLOUR, lw=3, marker="o", markersize=6,
                                 label="ellipse fit per 10 mm slab, centre dot"))
    if len(fid):
        handles.append(Line2D([], [], color=FIDUCIAL_COLOUR, marker="o", linestyle="none", markersize=9,
                              label=f"CT fiducials ({len(fid)} skin staples)"))
    return compose_figure(
        panels, size=size, titles=[title for title, _, _ in views], handles=handles,
        orientation=[o for _, _, o in views],
        suptitle=f"Heart model and heart frame in the patient frame, \u03c6C* = {phase} "
                 "(cf. Wood et al. 2018, Fig. 5)",
    )
