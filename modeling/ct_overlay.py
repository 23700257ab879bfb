"""The model over its CT: the surface's outline on planes of the CT (``model_ct.png``).

On a real CT the first question about a segmentation is where its surface runs
in the image: along the epicardium, up a vessel, into the liver.  The picture
answers it as a viewer would: four axial planes through the heart (at 20, 40,
60 and 80 % of its height) and a coronal and a sagittal plane through its
centre, the CT resampled on each plane (trilinear, any voxel orientation) and
the mesh's intersection with the plane drawn over it.  Radiological
orientation: axial and coronal planes show the patient's left on the right,
axial planes anterior up, coronal and sagittal planes superior up, sagittal
planes anterior on the left; each panel's edges carry the letters.

:func:`ct_panels` extracts the planes (small 2-D arrays) so that the CT can be
freed before :func:`render_ct_png` draws them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imaging.volume import OUTSIDE_HU

__all__ = ["CtPanel", "ct_panels", "render_ct_png"]

#: Axial planes at these fractions of the heart's height (from its lowest vertex).
AXIAL_LEVELS = (0.2, 0.4, 0.6, 0.8)
#: CT shown around the heart's box, mm.
MARGIN_MM = 15.0
#: Most pixels along a panel's longer side.
MAX_PIXELS = 360
#: Display window (HU): fat, myocardium and contrast blood apart; metal and bone saturate.
WINDOW_HU = (-250.0, 450.0)


@dataclass(frozen=True)
class CtPanel:
    """One plane of the CT with the model's outline, in the panel's own mm (``a`` right, ``b`` up).

    Attributes
    ----------
    title : str
    image : (n_b, n_a) float32
        HU on the plane, row 0 at ``extent[2]`` (the bottom).
    extent : (a0, a1, b0, b1) float, mm
    outline : (n, 2, 2) float
        Segments of the surface's intersection with the plane, ``(a, b)`` mm.
    letters : (left, right, bottom, top) str
        Patient directions at the panel's edges.
    origin_patient_mm : (3,) float
        The plane's point at ``(a, b) = (0, 0)``, patient frame (LPS).
    axes_patient : (2, 3) float
        The unit directions of ``a`` and ``b`` in the patient frame.
    """

    title: str
    image: np.ndarray
    extent: tuple
    outline: np.ndarray
    letters: tuple
    origin_patient_mm: np.ndarray
    axes_patient: np.ndarray

    def to_patient(self, ab) -> np.ndarray:
        """Panel ``(a, b)`` mm (..., 2) to patient LPS mm (..., 3)."""
        return self.origin_patient_mm + np.asarray(ab, dtype=float) @ self.axes_patient


#: (name, normal, a axis, b axis, letters at left, right, bottom, top) in LPS.
_VIEWS = {
    "axial": ((0, 0, 1), (1, 0, 0), (0, -1, 0), ("R", "L", "P", "A")),
    "coronal": ((0, 1, 0), (1, 0, 0), (0, 0, 1), ("R", "L", "I", "S")),
    "sagittal": ((1, 0, 0), (0, 1, 0), (0, 0, 1), ("A", "P", "I", "S")),
}


def plane_section(vertices, faces, origin, normal) -> np.ndarray:
    """Where a triangle mesh crosses a plane: (s, 2, 3) segments, one per crossing face.

    A vertex on the plane counts as on its positive side, so each crossing face
    has exactly two edges whose ends lie on opposite sides; the segment joins
    their crossings (linear along the edge); a face that touches the plane at
    one corner only gives none.  (trimesh's ``mesh_plane`` gives the same
    segments, except on a plane that holds flat faces of the mesh, where
    either may give or skip their edges; importing trimesh costs a quarter of
    a second of the model command.)
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    d = (v - np.asarray(origin, dtype=float)) @ np.asarray(normal, dtype=float)
    side = d[f] >= 0.0  # (m, 3)
    crossing = side.any(axis=1) & ~side.all(axis=1)
    f, side = f[crossing], side[crossing]
    # the vertex alone on its side, then the other two in the face's order
    lone = np.where(side.sum(axis=1) == 1, np.argmax(side, axis=1), np.argmin(side, axis=1))
    rows = np.arange(f.shape[0])
    a = f[rows, lone]
    ends = np.stack([f[rows, (lone + 1) % 3], f[rows, (lone + 2) % 3]], axis=1)  # (s, 2)
    t = d[a][:, None] / (d[a][:, None] - d[ends])  # (s, 2), in [0, 1]
    segments = v[a][:, None] + t[..., None] * (v[ends] - v[a][:, None])
    return segments[np.any(segments[:, 0] != segments[:, 1], axis=1)]  # not a face touching it at a corner


def _panel(hu, T_voxel_from_patient, mesh, title, origin, view, lo, hi) -> CtPanel:
    from scipy import ndimage

    *axes, letters = _VIEWS[view]
    normal, a_axis, b_axis = np.asarray(axes, dtype=float)
    # the heart's box on the plane, with a margin
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    a_range, b_range = ((p.min() - MARGIN_MM, p.max() + MARGIN_MM) for p in ((corners - origin) @ a_axis,
                                                                             (corners - origin) @ b_axis))
    step = max(max(a_range[1] - a_range[0], b_range[1] - b_range[0]) / MAX_PIXELS, 0.25)
    a = np.arange(a_range[0], a_range[1] + 1e-9, step)
    b = np.arange(b_range[0], b_range[1] + 1e-9, step)
    A, B = np.meshgrid(a, b)  # rows: b (bottom first), columns: a
    points = origin + A[..., None] * a_axis + B[..., None] * b_axis
    ijk = points.reshape(-1, 3) @ T_voxel_from_patient[:3, :3].T + T_voxel_from_patient[:3, 3]
    image = ndimage.map_coordinates(hu, ijk[:, ::-1].T, order=1, mode="constant", cval=OUTSIDE_HU,
                                    output=np.float32).reshape(A.shape)
    segments = plane_section(*mesh, origin, normal)
    outline = np.stack([(segments - origin) @ a_axis, (segments - origin) @ b_axis], axis=-1) \
        if len(segments) else np.zeros((0, 2, 2))
    half = 0.5 * step
    return CtPanel(title, image, (a[0] - half, a[-1] + half, b[0] - half, b[-1] + half), outline, letters,
                   np.asarray(origin, dtype=float), np.stack([a_axis, b_axis]))


def ct_panels(hu, T_patient_from_voxel, vertices_patient, faces) -> list[CtPanel]:
    """The CT on four axial planes through the heart and a coronal and a sagittal one through its centre.

    Parameters
    ----------
    hu : (n_k, n_j, n_i) array
        The CT, indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
    vertices_patient : (n, 3) float, mm (LPS)
    faces : (m, 3) int
        The model's surface in the patient frame.

    Returns
    -------
    list of CtPanel
    """
    v = np.asarray(vertices_patient, dtype=float)
    mesh = (v, np.asarray(faces))
    T_inv = np.linalg.inv(np.asarray(T_patient_from_voxel, dtype=float))
    hu = np.asarray(hu)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * (lo + hi)
    panels = []
    for level in AXIAL_LEVELS:
        z = lo[2] + level * (hi[2] - lo[2])
        panels.append(_panel(hu, T_inv, mesh, f"axial, {100 * level:.0f} % of the height (z {z:.0f} mm)",
                             np.array([centre[0], centre[1], z]), "axial", lo, hi))
    panels.append(_panel(hu, T_inv, mesh, f"coronal through the centre (y {centre[1]:.0f} mm)", centre, "coronal",
                         lo, hi))
    panels.append(_panel(hu, T_inv, mesh, f"sagittal through the centre (x {centre[0]:.0f} mm)", centre,
                         "sagittal", lo, hi))
    return panels


def render_ct_png(panels, path, *, suptitle: str = "Heart model over its CT: the surface's outline on each plane",
                  colour: str = "#ff5050") -> Path:
    """Draw :func:`ct_panels` to a PNG (matplotlib, no OpenGL; written atomically)."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure  # no pyplot: no global backend state, and its import is not needed

    from hrcore.figlayout import PNG_OPTIONS
    from imaging.files import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"path must end in .png, got {path.name}")
    columns = 3
    rows = -(-len(panels) // columns)
    fig = Figure(figsize=(4.2 * columns, 4.2 * rows + 0.5))
    axes = fig.subplots(rows, columns, squeeze=False)
    for ax, panel in zip(axes.flat, panels):
        ax.imshow(panel.image, cmap="gray", vmin=WINDOW_HU[0], vmax=WINDOW_HU[1], origin="lower",
                  extent=panel.extent, interpolation="nearest")  # ~1 image pixel per screen pixel
        ax.add_collection(LineCollection(panel.outline, colors=colour, linewidths=1.2))
        ax.set_xlim(panel.extent[:2])
        ax.set_ylim(panel.extent[2:])
        ax.set_title(panel.title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        for (x, y, ha, va), letter in zip(((0.02, 0.5, "left", "center"), (0.98, 0.5, "right", "center"),
                                           (0.5, 0.02, "center", "bottom"), (0.5, 0.98, "center", "top")),
                                          panel.letters):
            ax.text(x, y, letter, transform=ax.transAxes, ha=ha, va=va, color="#ffd000", fontsize=10,
                    fontweight="bold")
        a0, _, b0, _ = panel.extent
        ax.plot([a0 + 5, a0 + 25], [b0 + 5, b0 + 5], color="white", linewidth=2)
        ax.text(a0 + 15, b0 + 7, "20 mm", color="white", ha="center", va="bottom", fontsize=8)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    fig.suptitle(suptitle, fontsize=11, y=0.995)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=1 - 0.8 / (4.2 * rows + 0.5), wspace=0.04,
                        hspace=0.12)  # fixed margins: tight_layout would draw the figure once more
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90, pil_kwargs=PNG_OPTIONS)
    return path
