"""Pictures of the great vessels' origins on the anatomical phantom (what ``anatomy_accuracy.py`` measures).

For each vessel origin in a case written by ``bench/anatomy_accuracy.py``
(``bench/out/anatomy/<size>/``), two orthogonal CT planes through the vessel's
axis (``s`` mm along the vessel, 0 at its origin; ``t`` mm across it), with the
true epicardium (green), the automatic heart mask (orange) and the model mesh's
section (red), through the mouth's worst truth -> mesh point (yellow star).
PNG files go to ``<case>/slices/``.

    .venv/bin/python bench/anatomy_slices.py bench/out/anatomy/sample [--vessels aorta,pulmonary_trunk]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from heartreg.phantom import heart_from_truth  # noqa: E402

#: half-width (mm) and pixel (mm) of each picture
HALF_MM, PIXEL_MM = 40.0, 0.5


def _plane(volume_like, T_patient_from_voxel, centre, u, a, order):
    """Sample a (s, t) plane of ``volume_like`` (``[k, j, i]``) through ``centre`` spanned by ``u`` and ``a``."""
    from scipy import ndimage

    s = np.arange(-HALF_MM, HALF_MM + 1e-9, PIXEL_MM)
    S, T = np.meshgrid(s, s, indexing="ij")
    P = centre + S[..., None] * u + T[..., None] * a
    Ti = np.linalg.inv(T_patient_from_voxel)
    ijk = P @ Ti[:3, :3].T + Ti[:3, 3]
    img = ndimage.map_coordinates(np.asarray(volume_like, np.float32), ijk[..., ::-1].reshape(-1, 3).T, order=order)
    return s, P, img.reshape(S.shape)


def draw(case: Path, names=None) -> list[Path]:
    """Write the pictures of ``case``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from scipy.spatial import cKDTree

    from imaging import load_study
    from modeling import build_heart_model, segment_heart

    truth = json.loads((case / "truth.json").read_text())
    volume = load_study(case / "ct")
    T = volume.T_patient_from_voxel
    build = build_heart_model(volume, cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth")
    heart_mask = segment_heart(volume.hu, T).mask  # the mask build_heart_model meshes (default options)
    M = np.linalg.inv(build.model.T_heart_from_patient)
    mesh = trimesh.Trimesh(build.model.mesh.vertices @ M[:3, :3].T + M[:3, 3], build.model.mesh.faces, process=False)
    heart = heart_from_truth(truth)
    phase_c, phase_r = (truth["anatomy"]["epicardium"][k] for k in ("phase_c", "phase_r"))
    pts, _ = heart.sample_surface(phase_c, phase_r)
    samples, _ = trimesh.sample.sample_surface_even(mesh, 200_000, seed=0)
    back, _ = cKDTree(samples).query(pts)
    out = case / "slices"
    out.mkdir(exist_ok=True)
    written = []
    for o in truth["anatomy"]["vessel_origins"]:
        if names and o["name"] not in names:
            continue
        c, u = np.asarray(o["centre_patient_mm"]), np.asarray(o["direction_patient"])
        s_t = (pts - c) @ u
        r_t = np.linalg.norm((pts - c) - s_t[:, None] * u, axis=1)
        mouth = np.flatnonzero((r_t <= o["lumen_radius_mm"]) & (np.abs(s_t) <= 5.0))
        worst = pts[mouth[np.argmax(back[mouth])]] if mouth.size else c
        e = (worst - c) - ((worst - c) @ u) * u
        if np.linalg.norm(e) < 1e-3:
            e = np.cross(u, [0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.cross(u, [1.0, 0.0, 0.0])
        e /= np.linalg.norm(e)
        for tag, a in (("A", e), ("B", np.cross(u, e))):
            s, P, img = _plane(volume.hu, T, c, u, a, order=1)
            _, _, mask = _plane(heart_mask, T, c, u, a, order=0)
            d = heart.surface_distance(P.reshape(-1, 3), phase_c, phase_r).reshape(img.shape)
            fig, ax = plt.subplots(figsize=(7, 7))
            ax.imshow(img, cmap="gray", vmin=-200, vmax=600, origin="lower", extent=(s[0], s[-1], s[0], s[-1]))
            ax.contour(s, s, d, [0], colors="lime")
            ax.contour(s, s, mask, [0.5], colors="orange")
            section = mesh.section(plane_origin=c, plane_normal=np.cross(u, a))
            for line in [] if section is None else section.discrete:
                ax.plot((line - c) @ a, (line - c) @ u, "r-", lw=1)
            ax.plot([(worst - c) @ a], [(worst - c) @ u], "y*")
            ax.axhline(0.0, color="cyan", lw=0.5)
            ax.set(xlim=(s[0], s[-1]), ylim=(s[0], s[-1]), xlabel="t (mm)", ylabel="s along the vessel (mm)",
                   title=f"{o['name']} {tag}: truth green, mask orange, mesh red")
            path = out / f"{o['name']}_{tag}.png"
            fig.savefig(path, dpi=70)
            plt.close(fig)
            written.append(path)
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case", type=Path)
    ap.add_argument("--vessels", default=None, help="comma-separated origin names (default: all)")
    args = ap.parse_args(argv)
    for path in draw(args.case, args.vessels.split(",") if args.vessels else None):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
