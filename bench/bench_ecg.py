"""QRS detection on real ECG: ``imaging.detect_r_peaks`` vs neurokit2's default detector.

Data: the eight MIT-BIH Arrhythmia Database records of ``../shared/ecg/mitdb``
(30 min each, 360 Hz, 650 000 samples; see its README), read once per child
(untimed).  Each step times the detection on all eight records, one after the
other, in one fresh child (``common.run_step``); ours and neurokit2 alternate.

- ours: ``imaging.detect_r_peaks(ecg_mv, 360.0)``;
- reference: ``neurokit2.ecg_peaks(ecg_mv, sampling_rate=360)`` (default method
  "neurokit"), on the raw record as ours gets it, and, in a second row,
  ``ecg_clean`` (its default 0.5 Hz high-pass + powerline filter) followed by
  ``ecg_peaks``, the pipeline neurokit2 documents.

The notes give F1 over all beats (EC57: +-150 ms, one to one) of each, computed
untimed with the test's scorer (``tests/imaging/test_ecg_mitdb.py``).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

RECORDS = ("100", "102", "104", "105", "106", "108", "116", "119")


def _mitdb() -> Path:
    for base in (common.REPO_DIR.parent, common.REPO_DIR.parent.parent):
        folder = base / "shared" / "ecg" / "mitdb"
        if folder.is_dir():
            return folder
    raise common.BenchError("../shared/ecg/mitdb not found beside the repository")


def _records(folder: str):
    import numpy as np

    out = []
    for r in RECORDS:
        z = np.load(Path(folder) / f"{r}.npz")
        out.append((z["ecg_uv"] / 1000.0, float(z["fs_hz"]), z["r_peak_samples"] / float(z["fs_hz"])))
    return out


def _f1(results, records) -> float:
    sys.path.insert(0, str(common.REPO_DIR))
    from tests.imaging.test_ecg_mitdb import _scores, f1

    tp = fp = fn = 0
    for det, (_, _, ref) in zip(results, records):
        a, b, c, _ = _scores(det, ref)[0]
        tp, fp, fn = tp + a, fp + b, fn + c
    return f1(tp, fp, fn)


def detect_ours(folder: str) -> dict:
    import time

    from imaging import detect_r_peaks

    records = _records(folder)
    t0 = time.perf_counter()
    results = [detect_r_peaks(x, fs).times_s for x, fs, _ in records]
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "f1": _f1(results, records)}


def detect_neurokit(folder: str, clean: bool) -> dict:
    import time

    import neurokit2 as nk
    import numpy as np

    records = _records(folder)
    t0 = time.perf_counter()
    results = []
    for x, fs, _ in records:
        signal = nk.ecg_clean(x, sampling_rate=fs) if clean else x
        _, info = nk.ecg_peaks(signal, sampling_rate=fs)
        results.append(np.asarray(info["ECG_R_Peaks"], dtype=float) / fs)
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "f1": _f1(results, records)}


def main(argv=None) -> int:
    args = common.bench_argparser(__doc__.splitlines()[0]).parse_args(argv)
    folder = str(_mitdb())
    runs = common.run_steps_interleaved(
        {
            "ours": {"target": "bench_ecg:detect_ours", "kwargs": {"folder": folder},
                     "imports": ("numpy", "scipy.signal", "imaging.ecg")},
            "nk": {"target": "bench_ecg:detect_neurokit", "kwargs": {"folder": folder, "clean": False},
                   "imports": ("numpy", "neurokit2")},
            "nk_clean": {"target": "bench_ecg:detect_neurokit", "kwargs": {"folder": folder, "clean": True},
                         "imports": ("numpy", "neurokit2")},
        },
        repeats=args.repeats,
    )
    what = "QRS detection, 8 MIT-BIH records (8 x 30 min, 360 Hz)"
    f_ours = runs["ours"].info["f1"]
    rows = [
        common.Row(what, runs["ours"], runs["nk"], reference_name="neurokit2 ecg_peaks (default)",
                   notes=f"F1 over all beats: ours {100 * f_ours:.2f} %, neurokit2 {100 * runs['nk'].info['f1']:.2f} %; "
                         "imports untimed, runs interleaved"),
        common.Row(what + ", vs clean + peaks", runs["ours"], runs["nk_clean"],
                   reference_name="neurokit2 ecg_clean + ecg_peaks",
                   notes=f"F1 ours {100 * f_ours:.2f} %, neurokit2 after ecg_clean {100 * runs['nk_clean'].info['f1']:.2f} %"),
    ]
    common.write_results("bench_ecg", rows, command=common.command_line(), repeats=args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
