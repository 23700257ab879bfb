"""3-D view of a registration, like Fig. 8 of Wood et al. 2018.

Two panels of the heart model (heart frame, semi-opaque): on the left the
points registered by the fiducial registration ``T0``, on the right by the
final spatiotemporal registration.  Each point is the motion model's
prediction at (phi_C*, phi_R*), drawn as a sphere with an arrow along its
predicted surface normal (the robot's z axis).  Points are coloured by their
distance to the surface.  Rendering is offscreen pyvista
(:mod:`modeling.render` says what it needs); without offscreen OpenGL
:func:`render_registration_png` raises :class:`modeling.render.RenderError`
and the caller skips the picture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from modeling.model import HeartModel
from modeling.render import render_png
from registration.icp import SurfaceIndex, closest_points
from registration.result import RegistrationResult

__all__ = ["render_registration_png"]


def _mapped(T, points, normals):
    return points @ T[:3, :3].T + T[:3, 3], normals @ T[:3, :3].T


def render_registration_png(
    model: HeartModel,
    result: RegistrationResult,
    path,
    *,
    size: tuple[int, int] = (1300, 650),
) -> Path:
    """Draw the fiducial and the final registration side by side to a PNG.

    Parameters
    ----------
    model : HeartModel
        The model the result was registered to.
    result : RegistrationResult
    path : str or Path
        Output ``.png`` (written atomically).
    size : (width, height) int, pixels

    Returns
    -------
    Path

    Raises
    ------
    RenderError
        No offscreen OpenGL (the message says what to install), or VTK failed.
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    if not isinstance(result, RegistrationResult):
        raise TypeError(f"result must be a RegistrationResult, got {type(result).__name__}")
    if model.mesh.n_faces != result.n_faces:
        raise ValueError(
            f"the model has {model.mesh.n_faces} faces but the result was registered to a "
            f"mesh of {result.n_faces}: pass the model the session was registered to"
        )
    return render_png(lambda size: _draw(model, result, size=size), path, size=size, what="the registration")


def _draw(model: HeartModel, result: RegistrationResult, *, size) -> np.ndarray:
    import pyvista as pv

    pv.OFF_SCREEN = True
    mesh = model.mesh
    faces = np.hstack([np.full((mesh.n_faces, 1), 3), mesh.faces]).ravel()
    surf = pv.PolyData(np.asarray(mesh.vertices), faces)
    index = SurfaceIndex(mesh.vertices, mesh.faces)
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    arrow_mm = 0.12 * extent
    centre = mesh.vertices.mean(axis=0)
    panels = (
        ("(A) fiducial registration T0", result.T0_heart_from_probe),
        (f"(B) spatiotemporal registration, phi_R* = {result.phase_r:.2f}", result.T_heart_from_probe),
    )
    # the heart frame's x points anterior: look from there, z (base) up
    cam = centre + np.array([1.0, 0.35, 0.25]) * 3.2 * extent
    plotter = pv.Plotter(off_screen=True, window_size=size, shape=(1, 2), border=False)
    try:
        for col, (title, T) in enumerate(panels):
            plotter.subplot(0, col)
            plotter.set_background("white")
            plotter.add_mesh(surf, color="#d9a38f", opacity=0.6, smooth_shading=True)
            pts, nrm = _mapped(T, result.points_probe_mm, result.normals_probe)
            dist = closest_points(index, pts).distances_mm
            cloud = pv.PolyData(pts)
            cloud["distance (mm)"] = dist
            cloud["normal"] = nrm
            arrows = cloud.glyph(orient="normal", scale=False, factor=arrow_mm,
                                 geom=pv.Arrow(tip_length=0.3, tip_radius=0.12, shaft_radius=0.04))
            plotter.add_mesh(arrows, color="#1f4e9c")
            plotter.add_mesh(
                cloud, scalars="distance (mm)", render_points_as_spheres=True, point_size=11,
                cmap="viridis", clim=(0.0, max(5.0, float(np.ceil(dist.max())))),
                show_scalar_bar=col == 1,
                scalar_bar_args={"title": "to surface (mm)", "color": "black", "vertical": True,
                                 "position_x": 0.84, "position_y": 0.15, "width": 0.05,
                                 "height": 0.6, "title_font_size": 14, "label_font_size": 12},
            )
            rms = float(np.sqrt(np.mean(dist**2)))
            plotter.add_text(
                f"{title}\nRMS distance {rms:.2f} mm, {pts.shape[0]} points at phi_C* = "
                f"{result.phase_c:.2f}\narrows: predicted surface normals",
                font_size=9, color="black",
            )
            plotter.camera_position = [tuple(cam), tuple(centre), (0.0, 0.0, 1.0)]
            plotter.reset_camera()
        plotter.link_views()
        img = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    return np.asarray(img)
