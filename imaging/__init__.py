"""imaging: from a DICOM CT study on disk to a HU volume and per-slice cardiac phases.

Only this package touches ``pydicom`` datasets; later stages receive arrays,
affines and frozen dataclasses.
"""

from imaging.ecg import RPeaks, cardiac_phase, detect_r_peaks
from imaging.events import SignalError, phase_from_events
from imaging.nifti import is_nifti_path, read_nifti_volume
from imaging.phase import GatingError, GatingWarning, PhaseReport, SlicePhase, compute_phase_report, read_qrs_file
from imaging.phase_io import PhaseFileError, plot_phases, read_phase_report, write_phase_report
from imaging.respiration import expiration_onsets, respiration_phase
from imaging.grouping import SeriesSummary, StudyError, StudyWarning
from imaging.series import list_series, load_study
from imaging.pixels import DecoderUnavailableError, PixelDataError
from imaging.volume import (
    SeriesError,
    SeriesInfo,
    SliceInfo,
    Volume,
)
from imaging.waveform import EcgRecord, WaveformError, read_ecg_waveform

__all__ = [
    "DecoderUnavailableError",
    "EcgRecord",
    "GatingError",
    "GatingWarning",
    "PhaseReport",
    "PixelDataError",
    "RPeaks",
    "SeriesError",
    "SeriesInfo",
    "SeriesSummary",
    "SignalError",
    "SliceInfo",
    "SlicePhase",
    "StudyError",
    "StudyWarning",
    "Volume",
    "WaveformError",
    "cardiac_phase",
    "compute_phase_report",
    "detect_r_peaks",
    "expiration_onsets",
    "list_series",
    "load_study",
    "is_nifti_path",
    "phase_from_events",
    "read_nifti_volume",
    "plot_phases",
    "read_ecg_waveform",
    "read_qrs_file",
    "respiration_phase",
    "write_phase_report",
    "read_phase_report",
    "PhaseFileError",
]
