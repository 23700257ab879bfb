"""imaging: from a DICOM CT study on disk to a HU volume and per-slice cardiac phases.

Only this package touches ``pydicom`` datasets; later stages receive arrays,
affines and frozen dataclasses. The names below are what a caller needs: read a
study (:func:`load_study`), its cardiac phases (:func:`compute_phase_report`) and
the ECG and respiration signals behind them; everything else (file formats,
decoding, grouping rules, warnings) stays importable from its module.
The names are imported on first use (:mod:`hrcore.lazy`): a module of the
package (``imaging.files``, ``imaging.nrrd``) imports nothing else.
"""

from hrcore.lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "imaging.ecg": ("RPeaks", "cardiac_phase", "detect_r_peaks"),
    "imaging.grouping": ("SeriesSummary", "StudyError"),
    "imaging.volume_file": ("read_nifti_volume", "read_nrrd_volume", "read_volume_file"),
    "imaging.phase": ("GatingError", "PhaseReport", "compute_phase_report", "read_qrs_file"),
    "imaging.phase_io": ("plot_phases", "read_phase_report", "write_phase_report"),
    "imaging.respiration": ("expiration_onsets", "respiration_phase"),
    "imaging.series": ("list_series", "load_study"),
    "imaging.volume": ("SeriesError", "Volume"),
    "imaging.waveform": ("EcgRecord", "read_ecg_waveform"),
})

__all__ = [
    # a study
    "Volume",
    "SeriesSummary",
    "list_series",
    "load_study",
    "read_nifti_volume",
    "read_nrrd_volume",
    "read_volume_file",
    # its cardiac phases
    "PhaseReport",
    "compute_phase_report",
    "read_phase_report",
    "write_phase_report",
    "plot_phases",
    "read_qrs_file",
    # the signals
    "EcgRecord",
    "read_ecg_waveform",
    "RPeaks",
    "detect_r_peaks",
    "cardiac_phase",
    "expiration_onsets",
    "respiration_phase",
    # refusals (each a hrcore.HeartregError)
    "StudyError",
    "SeriesError",
    "GatingError",
]
