"""Reading a full-size CT study: ``imaging.load_study`` vs SimpleITK, and the phase report.

The study is a full-size phantom (512 x 512 x 288, int16, with GE cardiac private
tags and one ECG waveform DICOM in the same folder), generated once into
``bench/out/data/full_ct`` and reused.

Steps, each run in a fresh child process (see ``common.py``):

- ``load_study``: ``imaging.load_study(folder)`` -> ``Volume.hu``; the folder
  scan (every file, the ECG included), grouping, geometry checks and pixel
  decoding are all timed.
- reference: SimpleITK's ``ImageSeriesReader``: ``GetGDCMSeriesFileNames(folder,
  ct_series_uid)`` (the CT series only: the folder also holds the ECG waveform,
  which ITK cannot read as an image), ``Execute()``, and a zero-copy numpy view
  (``GetArrayViewFromImage``).  Target: ours <= 1.2 x SimpleITK.  The two run
  alternately (ours, SimpleITK, ours, ...) after one untimed read of every file,
  so both start from the same warm page cache.
- ``compute_phase_report``: on the loaded volume (volume load and ECG waveform
  read untimed, in the child).
- a correctness check (untimed): both HU arrays, each sorted by slice position
  along the common normal, are compared voxel by voxel.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

TARGET_RATIO = 1.2


# ---------------------------------------------------------------- steps (run in a child)


def read_ours(study_dir: str) -> dict:
    import imaging

    vol = imaging.load_study(study_dir)
    return {"shape": list(vol.hu.shape), "dtype": str(vol.hu.dtype), "nbytes": int(vol.hu.nbytes),
            "resampled": bool(vol.resampled), "series_uid": vol.series.series_instance_uid}


def read_sitk(study_dir: str, series_uid: str) -> dict:
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    files = reader.GetGDCMSeriesFileNames(study_dir, series_uid)
    reader.SetFileNames(files)
    image = reader.Execute()
    hu = sitk.GetArrayViewFromImage(image)
    return {"shape": list(hu.shape), "dtype": str(hu.dtype), "nbytes": int(hu.nbytes), "n_files": len(files)}


def phase_report(study_dir: str) -> dict:
    import imaging

    vol = imaging.load_study(study_dir)
    records = [imaging.read_ecg_waveform(p) for p in vol.waveform_files]
    t0 = time.perf_counter()
    report = imaging.compute_phase_report(vol, ecg_records=records)
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "source": report.source, "n_slices": int(report.n_slices),
            "volume_phase": float(report.volume_cardiac_phase)}


def compare(study_dir: str, series_uid: str) -> dict:
    """Both readers' HU arrays, each sorted by position along the slice normal."""
    import numpy as np
    import SimpleITK as sitk

    import imaging

    vol = imaging.load_study(study_dir)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(study_dir, series_uid))
    image = reader.Execute()
    ref = sitk.GetArrayViewFromImage(image)  # (z, y, x) in ITK's own slice order

    D = np.array(image.GetDirection()).reshape(3, 3)
    normal = np.cross(D[:, 0], D[:, 1])
    T = vol.T_patient_from_voxel
    k_ours = np.arange(vol.hu.shape[0])
    pos_ours = (T[:3, 2][None, :] * k_ours[:, None] + T[:3, 3]) @ normal
    k_ref = np.arange(ref.shape[0])
    ref_origin = np.array(image.GetOrigin())
    pos_ref = (ref_origin + np.outer(k_ref * image.GetSpacing()[2], D[:, 2])) @ normal
    order_ours, order_ref = np.argsort(pos_ours), np.argsort(pos_ref)
    out = {"shape_ours": list(vol.hu.shape), "shape_ref": list(ref.shape),
           "dtype_ours": str(vol.hu.dtype), "dtype_ref": str(ref.dtype),
           "ref_order": "ascending" if pos_ref[-1] > pos_ref[0] else "descending"}
    if vol.hu.shape != ref.shape:
        return {**out, "equal": False, "why": "shapes differ"}
    pos_diff_mm = float(np.max(np.abs(pos_ours[order_ours] - pos_ref[order_ref])))
    inplane_diff_mm = float(np.max(np.abs(T[:3, :2] - D[:, :2] * np.array(image.GetSpacing()[:2]))))
    max_abs = 0
    for a, b in zip(order_ours, order_ref):  # slice by slice: no full-size temporaries
        d = np.abs(vol.hu[a].astype(np.int32) - np.asarray(ref[b], dtype=np.float64).astype(np.int32))
        max_abs = max(max_abs, int(d.max()))
    return {**out, "equal": max_abs == 0 and pos_diff_mm < 1e-3, "max_abs_diff_hu": max_abs,
            "slice_position_diff_mm": pos_diff_mm, "inplane_axes_diff_mm": inplane_diff_mm}


# ---------------------------------------------------------------- the bench


def _ct_series_uid(study_dir: Path) -> str:
    import imaging

    cts = [s for s in imaging.list_series(study_dir) if s.modality == "CT"]
    return max(cts, key=lambda s: s.n_slices).uid


def main(argv=None) -> int:
    args = common.bench_argparser(__doc__.splitlines()[0]).parse_args(argv)
    common.ensure_requirements()
    study = common.ensure_phantom_case("full_ct") / "ct"
    uid = _ct_series_uid(study)
    me = "bench_imaging"
    n = args.repeats

    common.warm_page_cache(study)
    both = common.run_steps_interleaved({
        "ours": {"target": f"{me}:read_ours", "kwargs": {"study_dir": str(study)},
                 "imports": ("numpy", "pydicom", "imaging")},
        "ref": {"target": f"{me}:read_sitk", "kwargs": {"study_dir": str(study), "series_uid": uid},
                "imports": ("numpy", "SimpleITK")},
    }, repeats=n)
    ours, ref = both["ours"], both["ref"]
    check = common.run_step(f"{me}:compare", {"study_dir": str(study), "series_uid": uid}, repeats=1).info
    phases = common.run_step(f"{me}:phase_report", {"study_dir": str(study)}, repeats=n,
                             imports=("numpy", "pydicom", "imaging"))

    shape = "x".join(map(str, reversed(ours.info["shape"])))
    same = (f"same HU array as SimpleITK (sorted by position, max |diff| {check['max_abs_diff_hu']} HU)"
            if check["equal"] else f"HU arrays DIFFER: {check}")
    ratio = ours.median_s / ref.median_s
    verdict = "meets" if ratio <= TARGET_RATIO else "MISSES"
    rows = [
        common.Row(
            step=f"read full CT study ({shape} {ours.info['dtype']}, {len(list(study.iterdir()))} files)",
            ours=ours, reference=ref, reference_name="SimpleITK ImageSeriesReader",
            notes=(f"{verdict} target <= {TARGET_RATIO}x; volume {ours.info['nbytes'] / 2**20:.0f} MiB "
                   f"{ours.info['dtype']} (SimpleITK: {ref.info['nbytes'] / 2**20:.0f} MiB {ref.info['dtype']}); "
                   f"{same}; warm page cache, runs interleaved; "
                   f"baseline after imports {ours.info['baseline_mb']:.0f} / {ref.info['baseline_mb']:.0f} MB"),
            command=f"imaging.load_study('{study}')",
        ),
        common.Row(
            step="compute_phase_report (full CT)",
            ours=phases,
            notes=(f"source: {phases.info['source']}; {phases.info['n_slices']} slices; "
                   f"peak memory includes loading the volume"),
            command="imaging.compute_phase_report(volume, ecg_records=...)",
        ),
    ]
    common.write_results(me, rows, command=common.command_line(), repeats=n)
    return 0 if check["equal"] else 1


if __name__ == "__main__":
    sys.exit(main())
