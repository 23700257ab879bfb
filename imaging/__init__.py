"""imaging: from a DICOM CT study on disk to a HU volume and per-slice cardiac phases.

Only this package touches ``pydicom`` datasets; later stages receive arrays,
affines and frozen dataclasses. The names below are what a caller needs: read a
study (:func:`load_study`), its cardiac phases (:func:`compute_phase_report`) and
the ECG and respiration signals behind them; everything else (file formats,
decoding, grouping rules, warnings) stays importable from its module.
"""

from imaging.ecg import RPeaks, cardiac_phase, detect_r_peaks
from imaging.grouping import SeriesSummary, StudyError
from imaging.volume_file import read_nifti_volume, read_nrrd_volume, read_volume_file
from imaging.phase import GatingError, PhaseReport, compute_phase_report, read_qrs_file
from imaging.phase_io import plot_phases, read_phase_report, write_phase_report
from imaging.respiration import expiration_onsets, respiration_phase
from imaging.series import list_series, load_study
from imaging.volume import SeriesError, Volume
from imaging.waveform import EcgRecord, read_ecg_waveform

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
