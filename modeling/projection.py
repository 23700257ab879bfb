"""Parallel-projection views of a scene drawn by matplotlib alone (no OpenGL).

The model picture (:func:`modeling.render.render_model_png`) shows an 8k-face
semi-opaque surface, a few lines, arrows and balls.  Offscreen VTK draws that
through Mesa's llvmpipe: about 300 MB of JIT compiler and buffers and seconds of
shader compilation for one picture, more than the whole model stage on a
full-size CT.  Projected flat, the same scene is a painter's-algorithm drawing:
faces sorted back to front, shaded by their normal towards the viewer (two-sided,
as a translucent surface shows its inside), and the opaque parts drawn below the
surface or above it by their depth.

:func:`project_panel` returns an image and its scale like
:func:`modeling.render.render_panel`, so :func:`modeling.render.compose_figure`
lays out either.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Scene", "project_panel"]

#: Light on a face seen edge-on, and added for one facing the viewer (Lambert, headlight).
AMBIENT, DIFFUSE = 0.6, 0.4
#: Lines are drawn this much nearer than they are (as OpenGL's polygon offset): an
#: ellipse fitted to the surface's cross-section lies on it, and is not hidden by it.
LINE_OFFSET_MM = 1.0


@dataclass
class Scene:
    """What :func:`project_panel` draws; all positions in the same frame (mm).

    Attributes
    ----------
    surfaces : list of (vertices (n, 3), faces (m, 3), colour, opacity)
    lines : list of ((k, 3) polyline, colour, width_px)
    arrows : list of (start (3,), vector (3,), colour, shaft_radius_mm, tip_radius_mm, tip_length_mm)
    balls : list of (centre (3,), radius_mm, colour)
    """

    surfaces: list = field(default_factory=list)
    lines: list = field(default_factory=list)
    arrows: list = field(default_factory=list)
    balls: list = field(default_factory=list)

    def points(self) -> np.ndarray:
        """(n, 3) every position in the scene (for its extent)."""
        parts = [s[0] for s in self.surfaces] + [np.asarray(p[0], float) for p in self.lines]
        parts += [np.vstack([a[0], np.add(a[0], a[1])]) for a in self.arrows]
        parts += [np.reshape(b[0], (1, 3)) for b in self.balls]
        return np.vstack(parts)


def _basis(towards_camera, up):
    """Unit right, up and towards-camera axes of the picture (right = up x towards)."""
    towards = np.asarray(towards_camera, float) / np.linalg.norm(towards_camera)
    right = np.cross(up, towards)
    right /= np.linalg.norm(right)
    return right, np.cross(towards, right), towards


def project_panel(scene: Scene, *, size, towards_camera, up, focus) -> tuple[np.ndarray, float]:
    """One view of ``scene`` in parallel projection, drawn by matplotlib's Agg.

    Parameters
    ----------
    scene : Scene
    size : (width, height) int, pixels
    towards_camera, up : (3,) float
        Direction from the scene to the viewer, and the picture's up.
    focus : (3,) float, mm
        Point at the picture's centre.

    Returns
    -------
    image : (height, width, 3) uint8
        White background; the scene fills 90 % of the narrower fit.
    px_per_mm : float
        Pixels per millimetre in the picture (the same everywhere).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import to_rgb, to_rgba
    from matplotlib.figure import Figure

    width, height = (int(v) for v in size)
    right, up_axis, towards = _basis(towards_camera, up)
    to_picture = np.stack([right, up_axis], axis=1)  # (3, 2)
    focus = np.asarray(focus, float)
    uv = (scene.points() - focus) @ to_picture
    half = np.abs(uv).max(axis=0) + 1e-6
    px_per_mm = 0.9 * min(width / (2 * half[0]), height / (2 * half[1]))
    dpi = 100.0
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(-width / 2 / px_per_mm, width / 2 / px_per_mm)
    ax.set_ylim(-height / 2 / px_per_mm, height / 2 / px_per_mm)
    ax.set_axis_off()

    # every part as quadrilaterals in the picture with a depth (a triangle repeats a corner: one
    # array, matplotlib's fast path), drawn far to near; the balls, round, go in between
    polygons, depths, colours, smooth = [], [], [], []

    def add(quads, depth, rgba, antialiased):
        polygons.append(np.asarray(quads, float).reshape(-1, 4, 2))
        depths.append(np.broadcast_to(np.asarray(depth, float), (len(polygons[-1]),)))
        colours.append(np.broadcast_to(np.asarray(rgba, float), (len(polygons[-1]), 4)))
        smooth.append(np.full(len(polygons[-1]), antialiased))

    for vertices, faces, colour, opacity in scene.surfaces:
        v = np.asarray(vertices, float) - focus
        f = np.asarray(faces)
        tri = v[f]  # (m, 3, 3)
        area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        vertex_normal = np.zeros_like(v)
        for c in range(3):
            np.add.at(vertex_normal, f[:, c], area_normal)
        vertex_normal /= np.maximum(np.linalg.norm(vertex_normal, axis=1, keepdims=True), 1e-12)
        # smooth shading: the mean of the face's vertices' light, two-sided
        shade = (AMBIENT + DIFFUSE * np.abs(vertex_normal @ towards))[f].mean(axis=1)
        rgba = np.empty((len(f), 4))
        rgba[:, :3] = np.clip(np.outer(shade, to_rgb(colour)), 0.0, 1.0)
        rgba[:, 3] = opacity
        add((tri @ to_picture)[:, [0, 1, 2, 2]], tri.mean(axis=1) @ towards, rgba, False)

    def band(p3, half_width_mm, rgba):
        """A polyline as quads of one segment each (for their own depths)."""
        p3 = np.asarray(p3, float) - focus
        q = p3 @ to_picture
        d = np.diff(q, axis=0)
        n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        off = half_width_mm * n
        along = half_width_mm * np.stack([n[:, 1], -n[:, 0]], axis=1)  # overlapping ends: no seams
        a, b = q[:-1] - along, q[1:] + along
        quads = np.stack([a + off, b + off, b - off, a - off], axis=1)
        add(quads, 0.5 * (p3[:-1] + p3[1:]) @ towards + LINE_OFFSET_MM, rgba, True)

    for points, colour, width_px in scene.lines:
        band(points, 0.5 * width_px / px_per_mm, to_rgba(colour))
    for start, vector, colour, shaft_mm, tip_radius_mm, tip_mm in scene.arrows:
        start, vector = np.asarray(start, float), np.asarray(vector, float)
        length = float(np.linalg.norm(vector))
        neck = start + vector * (1.0 - tip_mm / length)
        band(start + np.linspace(0.0, 1.0, 25)[:, None] * (neck - start), shaft_mm, to_rgba(colour))
        d = vector @ to_picture
        if np.linalg.norm(d) > 1e-9:
            across = np.array([-d[1], d[0]]) / np.linalg.norm(d) * tip_radius_mm
            n2 = (neck - focus) @ to_picture
            add([n2 + across, (start + vector - focus) @ to_picture, n2 - across, n2 - across],
                (neck - focus) @ towards, to_rgba(colour), True)
    depth = np.concatenate(depths)
    order = np.argsort(depth, kind="stable")  # far to near
    quads, rgba = np.concatenate(polygons)[order], np.concatenate(colours)[order]
    antialiased, depth = np.concatenate(smooth)[order], depth[order]
    ring = np.stack([np.cos(np.linspace(0, 2 * np.pi, 33)), np.sin(np.linspace(0, 2 * np.pi, 33))], axis=1)
    balls = sorted(((float((np.asarray(c, float) - focus) @ towards) + r, np.asarray(c, float) - focus, r, colour)
                    for c, r, colour in scene.balls), key=lambda b: b[0])
    cuts = np.searchsorted(depth, [b[0] for b in balls]).tolist() + [len(depth)]
    start = 0
    for z, cut in enumerate(cuts):
        if cut > start:
            ax.add_collection(PolyCollection(quads[start:cut], facecolors=rgba[start:cut], edgecolors="none",
                                             linewidths=0.0, antialiaseds=list(antialiased[start:cut]), zorder=2 * z),
                              autolim=False)
        start = cut
        if z < len(balls):
            _, c, radius_mm, colour = balls[z]
            ax.add_collection(PolyCollection([c @ to_picture + radius_mm * ring], facecolors=[colour],
                                             edgecolors="#202020", linewidths=0.5, zorder=2 * z + 1),
                              autolim=False)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy(), float(px_per_mm)
