"""3-D view of a registration, like Fig. 8 of Wood et al. 2018.

Two panels of the heart model (heart frame, semi-opaque): on the left the
points registered by the fiducial registration ``T0``, on the right by the
final spatiotemporal registration.  Each point is the motion model's
prediction at (phi_C*, phi_R*), drawn as a sphere with an arrow along its
predicted surface normal (the robot's z axis).  Points are coloured by their
distance to the surface.  Drawn in parallel projection by matplotlib alone
(:mod:`modeling.projection`, as the model picture): no OpenGL is needed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hrcore.geometry import apply_to_points, apply_to_vectors
from modeling.model import HeartModel
from modeling.render import render_png
from registration.icp import SurfaceIndex, closest_points
from registration.result import RegistrationResult

__all__ = ["render_registration_png"]


def _mapped(T, points, normals):
    return apply_to_points(T, points), apply_to_vectors(T, normals)


def render_registration_png(
    model: HeartModel,
    result: RegistrationResult,
    path,
    *,
    size: tuple[int, int] = (1400, 720),
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
        The drawing failed or came out blank.

    Examples
    --------
    The view :func:`write_registration` writes as ``fig8_view.png``, of a
    registration read back with the model it was registered to (skipped here:
    the repository ships no registration):

    >>> from modeling import read_model
    >>> from registration import read_registration, render_registration_png
    >>> model = read_model("out/model")  # doctest: +SKIP
    >>> result = read_registration("out/registration")  # doctest: +SKIP
    >>> render_registration_png(model, result, "registration.png", size=(1000, 500))  # doctest: +SKIP
    PosixPath('registration.png')
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
    return render_png(lambda size: _draw(model, result, size=size), path, size=size, what="the registration",
                      opengl=False)


POINT_CMAP = "viridis"
ARROW_COLOUR = "#1f4e9c"
SURFACE_COLOUR = "#d9a38f"
#: radius of a registered point's ball in the view, mm.
POINT_RADIUS_MM = 1.6


def _draw(model: HeartModel, result: RegistrationResult, *, size) -> np.ndarray:
    from matplotlib import colormaps
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from modeling.projection import Scene, project_panel
    from modeling.render import compose_figure

    mesh = model.mesh
    index = SurfaceIndex(mesh.vertices, mesh.faces)
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    arrow_mm = 0.12 * extent
    centre = mesh.vertices.mean(axis=0)
    transforms = (result.T0_heart_from_probe, result.T_heart_from_probe)
    mapped = [_mapped(T, result.points_probe_mm, result.normals_probe) for T in transforms]
    dists = [closest_points(index, pts).distances_mm for pts, _ in mapped]
    vmax = max(5.0, float(np.ceil(max(d.max() for d in dists))))
    cmap = colormaps[POINT_CMAP]
    # the heart frame's x points anterior: look from the side of the points, z (base) up
    towards = mapped[1][0].mean(axis=0) - centre
    towards[2] = 0.35 * towards[2]
    towards = towards / np.linalg.norm(towards) if np.linalg.norm(towards) > 0 else np.array([1.0, 0.0, 0.0])

    def scene(pts, nrm, dist):
        # as pyvista's Arrow(tip_length=0.3, tip_radius=0.12, shaft_radius=0.04) scaled to arrow_mm
        return Scene(
            surfaces=[(mesh.vertices, mesh.faces, SURFACE_COLOUR, 0.6)],
            arrows=[(p, arrow_mm * n, ARROW_COLOUR, 0.04 * arrow_mm, 0.12 * arrow_mm, 0.3 * arrow_mm)
                    for p, n in zip(pts, nrm)],
            balls=[(p, POINT_RADIUS_MM, cmap(min(float(d) / vmax, 1.0))) for p, d in zip(pts, dist)],
        )

    panel = (max(size[0] // 2, 64), max(size[1], 64))  # each view at about the size it is shown, then cut
    panels = [project_panel(scene(p, n, d), size=panel, towards_camera=towards, up=(0.0, 0.0, 1.0), focus=centre)
              for (p, n), d in zip(mapped, dists)]
    rms = [float(np.sqrt(np.mean(d**2))) for d in dists]
    titles = [
        f"(A) fiducial registration $T_0$: RMS {rms[0]:.2f} mm",
        f"(B) spatiotemporal registration, $\\varphi_R^*$ = {result.respiration_phase:.2f}: RMS {rms[1]:.2f} mm",
    ]
    handles = [
        Patch(facecolor=SURFACE_COLOUR, alpha=0.7, edgecolor="none", label="heart model surface (heart frame)"),
        Line2D([], [], color=cmap(0.5), marker="o", linestyle="none", markersize=10, markeredgecolor="#333",
               label=f"registered point at ($\\varphi_C^*$, $\\varphi_R^*$), {len(dists[0])} points; "
                     "colour: distance to the surface"),
        Line2D([], [], color=ARROW_COLOUR, lw=3, label="arrow: predicted surface normal (robot z)"),
    ]
    return compose_figure(
        panels, size=size, titles=titles, handles=handles,
        suptitle=f"Registered points on the heart model at $\\varphi_C^*$ = {result.cardiac_phase:.2f} "
                 "(cf. Wood et al. 2018, Fig. 8)",
        colorbar=(cmap, 0.0, vmax, "distance to the surface (mm)"),
    )
