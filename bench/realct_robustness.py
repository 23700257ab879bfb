"""How ``heartreg model`` holds on the real CT of ``shared/realct`` altered as clinical scans differ.

Each case is the real CT (an ungated aortic CTA, 1.5 mm voxels) changed in one
way, written as a NIfTI and given to ``heartreg model`` with no options; the
model's mesh is scored on the CT's own grid against TotalSegmentator's heart
less its pulmonary artery (which heartreg cuts at the valve), as
``tests/modeling/test_realct.py`` does.  Cases: the CT as read; stored with
its axes in another order; resampled (linear) to 0.7 x 0.7 x 2.5 mm, 1.5 x
1.5 x 2.5 mm, 3 mm slices, 1 mm and 2 mm isotropic; white noise of 20, 40, 50, 70 and 100 HU
standard deviation, and 60 HU correlated over ~1.5 mm (a Gaussian of one
voxel); the blood within 12 mm of the heart dimmed 25 % and 50 % of the way
to 40 HU; cropped 2 cm at the top; a pacing lead (a 2 mm wire from the superior
vena cava through the right atrium to the right ventricle's apex) as a scanner
reconstructs it, mild and harsh, and an ICD's thicker shock lead
(:func:`_scanned_with_metal`: the streaks come from the physics, not painted).
A measurement, not a test: it prints a
Markdown table (and writes ``bench/out/realct_robustness.json``) and exits 0
whatever the numbers.

    .venv/bin/python bench/realct_robustness.py [--only NAME ...]

Session 15 found with a wider sweep of the same kind (and of the aortic CTA,
slicerio's CTChest4 and DICOM variants) the failures this table shows fixed:
a stub trim reading thin chamber walls as lumen (0.7 x 0.7 x 2.5 mm: Dice
0.71; dimmed 50 %: 0.78), speckled noise shrinking the left atrium's
inscribed radius until the vessel trace took it for vessels (noise 40 HU:
469 ml), a decimation leaving faces wound backwards (2.5 mm slices: 40000
faces kept, warned), and skin markers found in a scan without any when
stored (z, y, x).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from imaging.volume_file import read_nifti_volume  # noqa: E402
from modeling import read_model  # noqa: E402
from modeling.labelmap import mask_on_grid, read_label_map  # noqa: E402
from modeling.vessels import APEX_LAI_LPS  # noqa: E402
from tests.modeling.realct import LEAD_KJI, REALCT, mesh_to_mask, overlap  # noqa: E402

SPACING = (1.5, 1.5, 1.5)


def _resampled(hu, T, spacing_kji):
    from scipy import ndimage

    factors = np.linalg.norm(T[:3, :3], axis=0)[::-1] / np.asarray(spacing_kji, float)
    out = ndimage.zoom(hu.astype(np.float32), factors, order=1)
    T = T.copy()
    T[:3, :3] *= ((np.array(hu.shape) - 1) / (np.array(out.shape) - 1))[::-1]  # same corners
    return out, T


#: (name, wire radius mm, the metal's attenuation 1/mm, photons per ray): a pacing lead's conductor (about a
#: platinum-iridium coil's attenuation at 70 keV), the same with more beam hardening and fewer photons, and an
#: ICD's shock coil.
LEADS = (("pacing lead 2 mm (scanner simulated)", 1.0, 1.0, 3e3),
         ("pacing lead 2 mm, harsh (scanner simulated)", 1.0, 1.5, 1.5e3),
         ("ICD shock lead 3 mm (scanner simulated)", 1.5, 2.0, 1e3))


def _lead_fraction(shape_kji, path_kji, spacing_mm: float, radius_mm: float, sub: int = 4) -> np.ndarray:
    """Fraction of each voxel (isotropic ``spacing_mm``) within ``radius_mm`` of a wire along ``path_kji``
    (a cubic spline through the points), from ``sub`` samples per voxel along each axis."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial import cKDTree

    p = np.asarray(path_kji, float)
    t = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    line = CubicSpline(t, p)(np.linspace(0.0, t[-1], int(t[-1] * spacing_mm / 0.05)))  # a point every ~0.05 mm
    tree = cKDTree(line * spacing_mm)
    frac = np.zeros(shape_kji, np.float32)
    lo = np.maximum(np.floor(line.min(axis=0) - 3).astype(int), 0)
    hi = np.minimum(np.ceil(line.max(axis=0) + 4).astype(int), shape_kji)
    box = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    # supersample only the voxels the wire can reach (their centre within its radius and a half diagonal)
    box = box[np.isfinite(tree.query(box * spacing_mm, distance_upper_bound=radius_mm + 0.87 * spacing_mm)[0])]
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    d = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), -1).reshape(-1, 3)
    dist = tree.query(((box[:, None, :] + d) * spacing_mm).reshape(-1, 3), distance_upper_bound=radius_mm)[0]
    frac[tuple(box.T)] = np.isfinite(dist).reshape(len(box), -1).mean(axis=1)
    return frac


def _scanned_with_metal(hu, frac, spacing_mm: float, *, metal_mu_per_mm: float, photons: float,
                        hardening: float = 0.1, n_angles: int = 180, seed: int = 0):
    """``hu`` with metal (``frac`` of each voxel) as a scanner reconstructs it, slice by slice (parallel beam).

    Per slice holding metal: line integrals of the attenuation (``skimage.transform.radon``; water 0.0193 /mm),
    beam hardening as a quadratic loss on the metal's own line integral (``hardening * p_metal**2``), photon
    starvation as Poisson counts of ``photons * exp(-p)`` on the rays through metal.  The error these make,
    filtered back-projected (ramp), is added to the CT with the metal painted in (its partial volume at the
    metal's HU, clipped to 3071 as a 12-bit reconstruction is): the CT's own noise and resolution stay.
    """
    from skimage.transform import iradon, radon

    mu_water = 0.0193
    rng = np.random.default_rng(seed)
    hu = np.asarray(hu, np.float32)
    out = hu * (1 - frac) + 1000.0 * (metal_mu_per_mm / mu_water - 1) * frac
    theta = np.linspace(0.0, 180.0, n_angles, endpoint=False)
    n_j, n_i = hu.shape[1:]
    n = max(n_j, n_i)
    pad = ((n - n_j) // 2, n - n_j - (n - n_j) // 2), ((n - n_i) // 2, n - n_i - (n - n_i) // 2)
    for k in np.flatnonzero(frac.reshape(len(frac), -1).max(axis=1) > 0):
        mu = np.clip(mu_water * (1 + hu[k] / 1000.0), 0, None) * (1 - frac[k]) + metal_mu_per_mm * frac[k]
        p = radon(np.pad(mu, pad), theta, circle=False) * spacing_mm
        p_metal = radon(np.pad(metal_mu_per_mm * frac[k], pad), theta, circle=False) * spacing_mm
        measured = p - hardening * p_metal**2
        behind = p_metal > 1e-3
        counts = rng.poisson(photons * np.exp(-measured[behind]))
        measured[behind] = -np.log(np.maximum(counts, 0.5) / photons)
        error = iradon((measured - p) / spacing_mm, theta, circle=False, filter_name="ramp", output_size=n)
        out[k] += 1000.0 * error[pad[0][0]:pad[0][0] + n_j, pad[1][0]:pad[1][0] + n_i] / mu_water
    return np.rint(np.clip(out, -1024, 3071)).astype(np.int16)


def _cases(hu, T, reference, only=None):
    from scipy import ndimage

    near = ndimage.binary_dilation(reference, iterations=8)
    rng = np.random.default_rng(15)
    yield "as read", hu, T
    T_zyx = T[:, [2, 1, 0, 3]]
    yield "stored with its axes reversed", np.ascontiguousarray(hu.transpose(2, 1, 0)), T_zyx
    yield "0.7 x 0.7 x 2.5 mm (linear)", *_resampled(hu, T, (2.5, 0.7, 0.7))
    yield "1.5 x 1.5 x 2.5 mm (linear)", *_resampled(hu, T, (2.5, 1.5, 1.5))
    yield "3 mm slices (linear)", *_resampled(hu, T, (3.0, 1.5, 1.5))
    yield "1 mm isotropic (linear)", *_resampled(hu, T, (1.0, 1.0, 1.0))
    yield "2 mm isotropic (linear)", *_resampled(hu, T, (2.0, 2.0, 2.0))
    for sd in (20.0, 40.0, 50.0, 70.0, 100.0):
        yield f"white noise {sd:.0f} HU", hu + rng.normal(0.0, sd, hu.shape), T
    from scipy import ndimage

    texture = ndimage.gaussian_filter(rng.normal(0.0, 1.0, hu.shape), 1.0)  # noise correlated over ~1.5 mm, as CT's
    yield "correlated noise 60 HU", hu + texture * (60.0 / texture.std()), T
    for f in (0.25, 0.5):
        yield f"blood dimmed {f:.0%} towards 40 HU", np.where(near & (hu > 100), 40 + (hu - 40) * (1 - f), hu), T
    top = hu.shape[0] - int(round(20.0 / np.linalg.norm(T[:3, 2])))
    yield "cropped 2 cm at the top", hu[:top], T
    spacing = float(np.linalg.norm(T[:3, 0]))
    for name, radius, mu, photons in LEADS:
        if not (only and any(name.startswith(o) for o in only)):
            continue  # a simulated scan takes half a minute: only when asked for (--only pacing ICD)
        frac = _lead_fraction(hu.shape, LEAD_KJI, spacing, radius)
        yield name, _scanned_with_metal(hu, frac, spacing, metal_mu_per_mm=mu, photons=photons), T


def _write_nifti(hu, T, path):
    import nibabel as nib

    nib.save(nib.Nifti1Image(np.rint(hu).astype(np.int16).transpose(2, 1, 0), np.diag([-1.0, -1.0, 1.0, 1.0]) @ T),
             str(path))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="run the cases whose name starts with one of these")
    args = parser.parse_args(argv)
    volume = read_nifti_volume(REALCT / "ct_cropped.nii.gz")
    T = volume.T_patient_from_voxel
    reference = mask_on_grid(read_label_map(REALCT / "heart.nii.gz"), volume.shape, T)
    artery = mask_on_grid(read_label_map(REALCT / "pulmonary_artery.nii.gz"), volume.shape, T)
    target = reference & ~artery
    import os

    env = dict(os.environ, PYTHONPATH=str(HERE.parent))  # this checkout's heartreg, whatever is installed
    rows = []
    print("| case | exit | s | mesh ml | faces | Dice | MSD mm | p95 mm | apex . LAI "
          "| warnings beyond the CT as read |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    base_warnings = None
    with tempfile.TemporaryDirectory() as tmp:
        for name, hu, T_case in _cases(volume.hu, T, reference, args.only):
            if args.only and not any(name.startswith(o) for o in args.only):
                continue
            src, out = Path(tmp) / "ct.nii.gz", Path(tmp) / "model"
            _write_nifti(hu, T_case, src)
            t0 = time.perf_counter()
            run = subprocess.run([sys.executable, "-m", "heartreg", "model", str(src), "-o", str(out), "-q",
                                  "--overwrite"], capture_output=True, text=True, env=env)
            seconds = time.perf_counter() - t0
            row = dict(case=name, exit=run.returncode, seconds=round(seconds, 1))
            if run.returncode == 0:
                model = read_model(out)
                mesh = model.mesh_patient()
                m = overlap(mesh_to_mask(mesh.vertices, mesh.faces, volume.shape, T), target, SPACING)
                warned = [w.split(":")[0][:60] for w in model.parameters["warnings"]]
                base_warnings = warned if base_warnings is None else base_warnings
                row.update(mesh_ml=round(abs(mesh.volume_mm3) / 1000.0, 1), faces=len(mesh.faces),
                           **{k: round(v, 3) for k, v in m.items()},
                           apex=round(float(-model.frame.axes_patient[:, 2] @ APEX_LAI_LPS), 3),
                           warnings=[w for w in warned if w not in base_warnings])
            else:
                row.update(error=(run.stderr.strip().splitlines() or [""])[-1])
            rows.append(row)
            print(f"| {name} | {row['exit']} | {row['seconds']} | {row.get('mesh_ml', '-')} | {row.get('faces', '-')} "
                  f"| {row.get('dice', '-')} | {row.get('msd_mm', '-')} | {row.get('p95_mm', '-')} "
                  f"| {row.get('apex', '-')} "
                  f"| {'; '.join(row.get('warnings', [])) or row.get('error', '') or '-'} |",
                  flush=True)
    (HERE / "out").mkdir(exist_ok=True)
    (HERE / "out" / "realct_robustness.json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
