"""An interactive 3-D view for the HTML reports: one ``<figure>`` with everything inline.

:func:`viewer_html` returns HTML (a canvas, a legend, a small script and the
data) that draws a triangle mesh with point and line layers, rotatable with the
mouse or a finger, zoomable with the wheel, with a scale bar and the frame's
axes.  It needs no network, no library and no GPU: the drawing is a ~150-line
Canvas 2D renderer (back faces culled, the rest painted far to near, Lambert
shading), so the report stays one file that opens offline in any browser,
headless Chromium included (plotly would add 3.5 MB of JavaScript to every
report and WebGL is not there without a GPU; a mesh of 20 000 faces redraws in
a few tens of milliseconds this way).
"""

from __future__ import annotations

import base64
import html
import json
import re
from dataclasses import dataclass

import numpy as np

__all__ = ["Layer", "viewer_html"]

_COLOUR = re.compile(r"^#[0-9a-fA-F]{6}$")


@dataclass(frozen=True, eq=False)
class Layer:
    """Points or a polyline drawn over the mesh.

    Attributes
    ----------
    label : str
        Legend text.
    points_mm : (n, 3) float, mm
        Same frame as the mesh.
    colour : str
        ``#rrggbb``.
    kind : {"points", "line"}
        Discs at the points, or a polyline through them in order.
    size_px : float
        Disc diameter or line width, pixels.
    visible : bool
        Shown at first (the legend's box toggles it).
    """

    label: str
    points_mm: np.ndarray
    colour: str
    kind: str = "points"
    size_px: float = 7.0
    visible: bool = True

    def __post_init__(self):
        pts = np.asarray(self.points_mm, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"layer {self.label!r}: points_mm contains NaN or infinity")
        if self.kind not in ("points", "line"):
            raise ValueError(f"layer {self.label!r}: kind must be 'points' or 'line', got {self.kind!r}")
        if not _COLOUR.match(self.colour):
            raise ValueError(f"layer {self.label!r}: colour must be '#rrggbb', got {self.colour!r}")
        object.__setattr__(self, "points_mm", pts)


def _b64(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _view_rotation(view_from) -> np.ndarray:
    """Rows: the screen's right, up and towards-the-viewer axes in the mesh frame."""
    towards = np.array([1.0, 0.0, 0.0] if view_from is None else view_from, dtype=np.float64)
    if towards.shape != (3,) or not np.all(np.isfinite(towards)) or np.linalg.norm(towards) == 0:
        raise ValueError(f"view_from must be a non-zero 3-vector, got {view_from!r}")
    towards /= np.linalg.norm(towards)
    up = np.array([0.0, 0.0, 1.0])
    if abs(towards @ up) > 0.95:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(up, towards)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(towards, right), towards])


def viewer_html(
    vertices_mm,
    faces,
    *,
    layers=(),
    surface_label: str = "heart surface",
    surface_colour: str = "#d46a6a",
    axes_labels=("x", "y", "z"),
    frame_note: str = "",
    view_from=None,
    element_id: str = "view3d",
    size: tuple[int, int] = (960, 600),
) -> str:
    """HTML of an interactive view of a mesh with layers, self-contained.

    Parameters
    ----------
    vertices_mm : (n, 3) float, mm
    faces : (m, 3) int
        Triangles, counter-clockwise seen from outside (outward normals).
    layers : sequence of Layer
    surface_label, surface_colour : str
        Legend text and ``#rrggbb`` of the mesh.
    axes_labels : 3 str
        Labels of the frame's x, y, z axes (drawn red, green, blue).
    frame_note : str
        Shown under the view (e.g. "heart frame, mm").
    view_from : (3,) float, optional
        Direction from the mesh's centre towards the first camera position
        (default +x); the frame's z points up as far as it can.
    element_id : str
        HTML id of the figure (letters, digits, ``-``, ``_``).
    size : (width, height) int, pixels

    Returns
    -------
    str
        A ``<figure>`` element with its data and script inline.
    """
    v = np.asarray(vertices_mm, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not len(v):
        raise ValueError(f"vertices_mm must have shape (n, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= len(v))):
        raise ValueError(f"faces must be (m, 3) indices into the {len(v)} vertices")
    if not re.match(r"^[A-Za-z][\w-]*$", element_id):
        raise ValueError(f"element_id must be an HTML id, got {element_id!r}")
    if not _COLOUR.match(surface_colour):
        raise ValueError(f"surface_colour must be '#rrggbb', got {surface_colour!r}")
    width, height = (int(s) for s in size)
    data = {
        "view": _view_rotation(view_from).ravel().tolist(),
        "vertices": _b64(v, "<f4"),
        "faces": _b64(f, "<u4"),
        "surface": surface_colour,
        "axes": list(axes_labels),
        "layers": [
            {"kind": layer.kind, "colour": layer.colour, "size": float(layer.size_px), "visible": layer.visible,
             "points": np.round(layer.points_mm, 3).ravel().tolist()}
            for layer in layers
        ],
    }
    legend = [f'<li><span class="sw" style="background:{surface_colour}"></span>{html.escape(surface_label)}</li>']
    for k, layer in enumerate(layers):
        mark = ("sw dot" if layer.kind == "points" else "sw bar")
        checked = " checked" if layer.visible else ""
        legend.append(
            f'<li><label><input type="checkbox" data-layer="{k}"{checked}>'
            f'<span class="{mark}" style="background:{layer.colour}"></span>{html.escape(layer.label)}</label></li>'
        )
    axes = ", ".join(f'<b style="color:{c}">{html.escape(a)}</b>'
                     for a, c in zip(axes_labels, ("#d62728", "#2ca02c", "#1f4fd6")))
    legend.append(f"<li>frame axes: {axes} (bottom right); scale bar bottom left</li>")
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return (
        f'<figure class="view3d" id="{element_id}">'
        f"<style>{_CSS}</style>"
        f'<canvas width="{width}" height="{height}" '
        f'aria-label="interactive 3-D view: drag to rotate, wheel to zoom"></canvas>'
        f'<ul class="legend">{"".join(legend)}</ul>'
        f'<figcaption class="note">Drag to rotate, wheel (or pinch) to zoom, double-click to reset. '
        f"{html.escape(frame_note)}</figcaption>"
        f'<script type="application/json">{payload}</script>'
        f"<script>{_JS.replace('__ID__', element_id)}</script></figure>"
    )


_CSS = """
.view3d canvas { width: 100%; max-width: 960px; height: auto; border: 1px solid #ddd; cursor: grab;
                 touch-action: none; display: block; }
.view3d .legend { list-style: none; padding: 0; margin: .4em 0; display: flex; flex-wrap: wrap; gap: .3em 1.4em;
                  font-size: 15px; }
.view3d .sw { display: inline-block; width: 14px; height: 14px; margin: 0 .4em 0 .2em; vertical-align: -2px;
              border: 1px solid #333; }
.view3d .sw.dot { border-radius: 50%; } .view3d .sw.bar { height: 4px; vertical-align: 3px; border: 0; }
"""

_JS = r"""
(function () {
  const root = document.getElementById("__ID__");
  const cv = root.querySelector("canvas"), g = cv.getContext("2d");
  const D = JSON.parse(root.querySelector('script[type="application/json"]').textContent);
  function b64(s, T) {
    const bin = atob(s), u = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
    return new T(u.buffer);
  }
  const V = b64(D.vertices, Float32Array), F = b64(D.faces, Uint32Array);
  const nv = V.length / 3, nf = F.length / 3;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < nv; i++) for (let k = 0; k < 3; k++) {
    lo[k] = Math.min(lo[k], V[3 * i + k]); hi[k] = Math.max(hi[k], V[3 * i + k]);
  }
  const C = [0, 1, 2].map(k => (lo[k] + hi[k]) / 2);
  const radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2;
  const base = [1, 3, 5].map(i => parseInt(D.surface.substr(i, 2), 16));
  const L = [0.45, 0.55, 0.70], Ln = Math.hypot(L[0], L[1], L[2]);
  let R, zoom;
  function mul(A, B) {
    const M = [];
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++)
      M.push(A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]);
    return M;
  }
  function rotY(a) { const c = Math.cos(a), s = Math.sin(a); return [c, 0, s, 0, 1, 0, -s, 0, c]; }
  function rotX(a) { const c = Math.cos(a), s = Math.sin(a); return [1, 0, 0, 0, c, -s, 0, s, c]; }
  function reset() { R = D.view.slice(); zoom = 1.12; }
  reset();
  function draw() {
    const W = cv.width, H = cv.height, s = zoom * Math.min(W, H) / (2 * radius);
    g.fillStyle = "#ffffff"; g.fillRect(0, 0, W, H);
    const P = new Float64Array(nv * 3);
    for (let i = 0; i < nv; i++) {
      const x = V[3 * i] - C[0], y = V[3 * i + 1] - C[1], z = V[3 * i + 2] - C[2];
      P[3 * i] = R[0] * x + R[1] * y + R[2] * z;
      P[3 * i + 1] = R[3] * x + R[4] * y + R[5] * z;
      P[3 * i + 2] = R[6] * x + R[7] * y + R[8] * z;
    }
    const items = [];  // [depth, kind, index, shade]
    for (let f = 0; f < nf; f++) {
      const a = 3 * F[3 * f], b = 3 * F[3 * f + 1], c = 3 * F[3 * f + 2];
      const e1x = P[b] - P[a], e1y = P[b + 1] - P[a + 1], e1z = P[b + 2] - P[a + 2];
      const e2x = P[c] - P[a], e2y = P[c + 1] - P[a + 1], e2z = P[c + 2] - P[a + 2];
      const nx = e1y * e2z - e1z * e2y, ny = e1z * e2x - e1x * e2z, nz = e1x * e2y - e1y * e2x;
      if (nz <= 0) continue;  // faces away: hidden on a closed surface
      const n = Math.hypot(nx, ny, nz) || 1;
      const lam = Math.max(0, (nx * L[0] + ny * L[1] + nz * L[2]) / (n * Ln));
      items.push([(P[a + 2] + P[b + 2] + P[c + 2]) / 3, 0, f, 0.35 + 0.65 * lam]);
    }
    const lift = 0.02 * radius;  // marks sit on the surface: draw them just in front of it
    const layerPts = D.layers.map(layer => {
      const p = layer.points, q = [];
      for (let i = 0; i < p.length; i += 3) {
        const x = p[i] - C[0], y = p[i + 1] - C[1], z = p[i + 2] - C[2];
        q.push([R[0] * x + R[1] * y + R[2] * z, R[3] * x + R[4] * y + R[5] * z, R[6] * x + R[7] * y + R[8] * z]);
      }
      return q;
    });
    D.layers.forEach((layer, k) => {
      if (!layer.visible) return;
      const q = layerPts[k];
      if (layer.kind === "points") q.forEach((p, i) => items.push([p[2] + 1.5 * lift, 1, k, i]));
      else for (let i = 0; i + 1 < q.length; i++) items.push([(q[i][2] + q[i + 1][2]) / 2 + lift, 2, k, i]);
    });
    items.sort((u, v) => u[0] - v[0]);
    const X = x => W / 2 + s * x, Y = y => H / 2 - s * y;
    g.lineJoin = "round";
    for (const [, kind, k, extra] of items) {
      if (kind === 0) {
        const a = 3 * F[3 * k], b = 3 * F[3 * k + 1], c = 3 * F[3 * k + 2];
        const col = "rgb(" + base.map(v => Math.round(v * extra)).join(",") + ")";
        g.fillStyle = col; g.strokeStyle = col; g.lineWidth = 0.6;
        g.beginPath(); g.moveTo(X(P[a]), Y(P[a + 1])); g.lineTo(X(P[b]), Y(P[b + 1]));
        g.lineTo(X(P[c]), Y(P[c + 1])); g.closePath(); g.fill(); g.stroke();
      } else if (kind === 1) {
        const p = layerPts[k][extra], layer = D.layers[k];
        g.fillStyle = layer.colour; g.strokeStyle = "#222"; g.lineWidth = 1;
        g.beginPath(); g.arc(X(p[0]), Y(p[1]), layer.size / 2, 0, 2 * Math.PI); g.fill(); g.stroke();
      } else {
        const p = layerPts[k][extra], r = layerPts[k][extra + 1], layer = D.layers[k];
        g.strokeStyle = layer.colour; g.lineWidth = layer.size;
        g.beginPath(); g.moveTo(X(p[0]), Y(p[1])); g.lineTo(X(r[0]), Y(r[1])); g.stroke();
      }
    }
    // scale bar (bottom left): a round length of 60-160 px at this zoom
    const nice = [1, 2, 5, 10, 20, 25, 50, 100, 200, 500];
    let len = nice[0];
    for (const n of nice) if (n * s <= 160) len = n;
    const x0 = 24, y0 = H - 28;
    g.fillStyle = "#111"; g.fillRect(x0, y0, len * s, 5);
    g.fillRect(x0, y0 - 6, 2, 17); g.fillRect(x0 + len * s - 2, y0 - 6, 2, 17);
    g.font = "bold 17px sans-serif"; g.textBaseline = "bottom"; g.fillText(len + " mm", x0, y0 - 8);
    // frame axes (bottom right)
    const ax = W - 70, ay = H - 70, cols = ["#d62728", "#2ca02c", "#1f4fd6"];
    for (let k = 0; k < 3; k++) {
      const dx = R[k] * 44, dy = R[3 + k] * 44;
      g.strokeStyle = cols[k]; g.lineWidth = 3.5;
      g.beginPath(); g.moveTo(ax, ay); g.lineTo(ax + dx, ay - dy); g.stroke();
      g.fillStyle = cols[k]; g.font = "bold 17px sans-serif"; g.textBaseline = "middle";
      g.fillText(D.axes[k], ax + dx * 1.22 - 5, ay - dy * 1.22);
    }
  }
  let pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; draw(); }); } }
  let drag = null;
  cv.addEventListener("pointerdown", e => { drag = [e.clientX, e.clientY]; cv.setPointerCapture(e.pointerId); });
  cv.addEventListener("pointerup", () => { drag = null; });
  cv.addEventListener("pointermove", e => {
    if (!drag) return;
    const dx = e.clientX - drag[0], dy = e.clientY - drag[1];
    drag = [e.clientX, e.clientY];
    R = mul(rotX(dy * 0.01), mul(rotY(dx * 0.01), R));
    redraw();
  });
  cv.addEventListener("wheel", e => {
    e.preventDefault(); zoom = Math.min(20, Math.max(0.2, zoom * Math.exp(-e.deltaY * 0.0015))); redraw();
  }, { passive: false });
  cv.addEventListener("dblclick", () => { reset(); redraw(); });
  root.querySelectorAll("input[data-layer]").forEach(box => box.addEventListener("change", () => {
    D.layers[+box.dataset.layer].visible = box.checked; redraw();
  }));
  draw();
})();
"""
