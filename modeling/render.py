"""Offscreen PNG of a heart model, like Fig. 5 of Wood et al. 2018.

Two views of the patient frame side by side: approximately coronal (seen from
the front, patient's left on the picture's right) and approximately sagittal
(seen from the patient's left). The mesh is drawn semi-opaque, the slab ellipses
as yellow lines, the heart frame's x, y, z as red, green, blue arrows, the
fiducials as grey spheres.

Offscreen OpenGL: VTK picks its window from ``VTK_DEFAULT_OPENGL_WINDOW``
(``vtkOSOpenGLRenderWindow`` needs Debian's ``libosmesa6``;
``vtkEGLRenderWindow`` needs ``libegl1 libgl1``); without the variable and
without an X display, VTK 9.4+ falls back to EGL. Because a missing GL stack
can abort the process inside VTK, :func:`offscreen_available` first probes it
in a subprocess; when it fails :func:`render_model_png` raises
:class:`RenderError` and the caller skips the picture.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from imaging.files import atomic_path
from modeling.model import HeartModel

__all__ = ["RenderError", "offscreen_available", "render_model_png", "render_png"]


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


@functools.lru_cache(maxsize=1)
def offscreen_available(timeout_s: float = 60.0) -> bool:
    """Whether pyvista can draw offscreen here (probed once, in a subprocess)."""
    try:
        res = subprocess.run(
            [sys.executable, "-c", _PROBE],
            capture_output=True,
            text=True,
            timeout=timeout_s,
            env=os.environ.copy(),
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return res.returncode == 0 and res.stdout.strip().endswith("ok")


def render_model_png(
    model: HeartModel,
    path,
    *,
    ellipses: bool = True,
    size: tuple[int, int] = (900, 700),
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
        Offscreen rendering is not available or produced a blank image; the
        message says which libraries to install.
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    return render_png(lambda size: _draw(model, ellipses=ellipses, size=size), path, size=size, what="the model")


def render_png(draw, path, *, size: tuple[int, int], what: str) -> Path:
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
    if not offscreen_available():
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

    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")
    return path


def _draw(model: HeartModel, *, ellipses: bool, size) -> np.ndarray:
    import pyvista as pv

    pv.OFF_SCREEN = True
    mesh = model.mesh_patient()
    faces = np.hstack([np.full((mesh.n_faces, 1), 3), mesh.faces]).ravel()
    surf = pv.PolyData(np.asarray(mesh.vertices), faces)
    frame = model.frame
    origin = frame.origin_patient_mm
    axes = frame.axes_patient
    extent = np.ptp(mesh.vertices, axis=0).max()
    arrow_mm = 0.75 * extent

    plotter = pv.Plotter(off_screen=True, window_size=size, shape=(1, 2), border=False)
    try:
        views = (
            ("coronal (from anterior)", (0.0, -1.0, 0.0)),
            ("sagittal (from patient left)", (1.0, 0.0, 0.0)),
        )
        for col, (title, towards_camera) in enumerate(views):
            plotter.subplot(0, col)
            plotter.set_background("white")
            plotter.add_mesh(surf, color="#d46a6a", opacity=0.55, smooth_shading=True)
            if ellipses:
                for e in frame.ellipses:
                    ring = e.points(96)
                    line = pv.lines_from_points(np.vstack([ring, ring[:1]]))
                    plotter.add_mesh(line, color="#e0b000", line_width=3)
                    plotter.add_mesh(pv.Sphere(radius=1.2, center=e.centre_mm), color="#e0b000")
            for axis, colour in zip(axes.T, ("red", "green", "blue")):
                arrow = pv.Arrow(
                    start=origin, direction=axis, scale=arrow_mm,
                    tip_length=0.12, tip_radius=0.04, shaft_radius=0.015,
                )
                plotter.add_mesh(arrow, color=colour)
            for f in model.fiducials_patient_mm:
                plotter.add_mesh(pv.Sphere(radius=2.5, center=f), color="#606060")
            plotter.add_text(
                f"{title}\nphi_C = {'unknown' if model.cardiac_phase is None else format(model.cardiac_phase, '.2f')}  "
                "x red, y green, z blue",
                font_size=9, color="black",
            )
            centre = origin
            cam = np.asarray(towards_camera) * 4.0 * extent + centre
            plotter.camera_position = [tuple(cam), tuple(centre), (0.0, 0.0, 1.0)]
            plotter.reset_camera()
        img = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    return np.asarray(img)
