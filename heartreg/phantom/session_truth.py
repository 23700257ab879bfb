"""What the phantom's session generator knows and a registration must recover.

:class:`SessionTruth` (and one :class:`SessionPointTruth` per robot point) is
returned by :func:`heartreg.phantom.write_session`: the true transforms, the
event times, the noise actually written, the surface points in the heart frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from heartreg.phantom.heart import AnalyticHeart


@dataclass(frozen=True, eq=False)
class SessionPointTruth:
    """Ground truth of one attachment point.

    Attributes
    ----------
    point_id : int
        Record id and surface-point id in ``session.json``.
    u, v : float
        Surface coordinates of :meth:`AnalyticHeart.reference_points`.
    yaw_deg : float
        Fixed rotation of the robot about the surface normal.
    reference_heart_mm : (3,) float64
        End-diastolic reference point, heart construction frame.
    position_patient_mm, normal_patient : (3,) float64
        Position (mm) and outward unit normal in the patient frame at
        ``(config.gating_target_phase, config.image_resp_phase)``.
    start_s, end_s : float
        Times of the record's first and last sample, s after midnight.
    heart_rate_hz, resp_rate_hz : float
        Mean rates over the record.
    position_noise_rms_mm : (3,) float64
        RMS per probe axis of measured minus clean ``T_probe_from_robot``
        translation (as written to the file).
    rotation_noise_rms_deg : float
        RMS angle of measured relative to clean ``T_probe_from_robot`` rotation.
    """

    point_id: int
    u: float
    v: float
    yaw_deg: float
    reference_heart_mm: np.ndarray
    position_patient_mm: np.ndarray
    normal_patient: np.ndarray
    start_s: float
    end_s: float
    heart_rate_hz: float
    resp_rate_hz: float
    position_noise_rms_mm: np.ndarray
    rotation_noise_rms_deg: float

    def to_dict(self) -> dict:
        return {
            "id": self.point_id,
            "u": self.u,
            "v": self.v,
            "yaw_deg": self.yaw_deg,
            "reference_heart_mm": self.reference_heart_mm.tolist(),
            "position_patient_mm": self.position_patient_mm.tolist(),
            "normal_patient": self.normal_patient.tolist(),
            "start_s": self.start_s,
            "end_s": self.end_s,
            "heart_rate_hz": self.heart_rate_hz,
            "resp_rate_hz": self.resp_rate_hz,
            "position_noise_rms_mm": self.position_noise_rms_mm.tolist(),
            "rotation_noise_rms_deg": self.rotation_noise_rms_deg,
        }


@dataclass(frozen=True, eq=False)
class SessionTruth:
    """What the session generator knows and the registration must recover.

    Attributes
    ----------
    T_patient_from_probe : (4, 4) float64
        T*, the reference probe in the CT patient frame.
    T_fiducial_shift : (4, 4) float64
        CT-to-surgery skin motion (patient frame): staples in surgery are
        ``T_fiducial_shift @ f_ct``.
    T0_patient_from_probe : (4, 4) float64
        The fiducial registration a correct SVD of the touched (probe frame)
        onto the CT fiducials gives; ~ ``inv(T_fiducial_shift) @ T*``.
    T_tracker_from_patient : (4, 4) float64
        Nominal placement of the tracker (before drift and breathing).
    fiducials_ct_mm, fiducials_probe_mm : (9, 3) float64
        CT staple centres (patient frame) and the touched staples as written
        (probe frame), documented order.
    r_peaks_s, expiration_onsets_s : (n,) float64
        Event times on the session clock, s after midnight.
    image_phase_c, image_phase_r : float
        Phases of ``position_patient_mm`` (the gating target and the CT
        breath-hold phase of the config; the true image phase phi_C* is the
        CT writer's business).
    points : tuple of SessionPointTruth
    probe_breathing_mm : float
        Chest-wall excursion of the probe along its z, full breath.
    position_noise_rms_mm : (3,) float64
        RMS per probe axis over all samples of all points.
    rotation_noise_rms_deg : float
    fiducial_touch_rms_mm : float
        RMS per axis of touched minus true staples (true: where the CT saw them,
        moved by the CT-to-surgery shift; the chest wall's breathing included).
    chest_wall_ap_mm : float
        Sternal anterior excursion over a breath.
    fiducial_touch_phase_r : (9,) float64
        Respiration phase of each single touch (``fiducials.csv``).
    fiducial_trace_file : str
        The stylus trace (format 2), or "" (format 1).
    heart_rate_hz, resp_rate_hz : float
        Means over points of the per-record rates (as the paper's Table 1).
    """

    T_patient_from_probe: np.ndarray
    T_fiducial_shift: np.ndarray
    T0_patient_from_probe: np.ndarray
    T_tracker_from_patient: np.ndarray
    fiducials_ct_mm: np.ndarray
    fiducials_probe_mm: np.ndarray
    r_peaks_s: np.ndarray
    expiration_onsets_s: np.ndarray
    image_phase_c: float
    image_phase_r: float
    points: tuple[SessionPointTruth, ...]
    probe_breathing_mm: float
    position_noise_rms_mm: np.ndarray
    rotation_noise_rms_deg: float
    fiducial_touch_rms_mm: float
    heart_rate_hz: float
    resp_rate_hz: float
    chest_wall_ap_mm: float = 0.0
    fiducial_touch_phase_r: np.ndarray | None = None
    fiducial_trace_file: str = ""

    @property
    def u(self) -> np.ndarray:
        """(n,) float64 surface coordinate u of every point, in point order."""
        return np.array([p.u for p in self.points])

    @property
    def v(self) -> np.ndarray:
        """(n,) float64 surface coordinate v of every point, in point order."""
        return np.array([p.v for p in self.points])

    def positions_at(self, heart: AnalyticHeart, phase_c: float, phase_r: float) -> np.ndarray:
        """Patient-frame positions of all points at ``(phase_c, phase_r)``.

        Parameters
        ----------
        heart : AnalyticHeart
            The phantom heart (``layout.make_heart(config)``).
        phase_c, phase_r : float
            Cardiac and respiration phases in [0, 1).

        Returns
        -------
        (n, 3) float64, mm, patient frame
        """
        u, v = self.u, self.v
        return heart.surface_points(u, v, np.full(u.shape, phase_c), np.full(u.shape, phase_r))

    def frames_at(self, heart: AnalyticHeart, phase_c: float, phase_r: float):
        """Positions (n, 3) mm and surface frames (n, 3, 3) (z the outward normal)
        of all points at ``(phase_c, phase_r)``, patient frame."""
        u, v = self.u, self.v
        return heart.surface_frames(u, v, np.full(u.shape, phase_c), np.full(u.shape, phase_r))

    def to_dict(self) -> dict:
        """JSON-ready dictionary (lists and floats)."""
        return {
            "T_patient_from_probe": self.T_patient_from_probe.tolist(),
            "T_fiducial_shift": self.T_fiducial_shift.tolist(),
            "T0_patient_from_probe": self.T0_patient_from_probe.tolist(),
            "T_tracker_from_patient": self.T_tracker_from_patient.tolist(),
            "fiducials_ct_mm": self.fiducials_ct_mm.tolist(),
            "fiducials_probe_mm": self.fiducials_probe_mm.tolist(),
            "r_peaks_s": self.r_peaks_s.tolist(),
            "expiration_onsets_s": self.expiration_onsets_s.tolist(),
            "image_phase_c": self.image_phase_c,
            "image_phase_r": self.image_phase_r,
            "points": [p.to_dict() for p in self.points],
            "probe_breathing_mm": self.probe_breathing_mm,
            "position_noise_rms_mm": self.position_noise_rms_mm.tolist(),
            "rotation_noise_rms_deg": self.rotation_noise_rms_deg,
            "fiducial_touch_rms_mm": self.fiducial_touch_rms_mm,
            "heart_rate_hz": self.heart_rate_hz,
            "resp_rate_hz": self.resp_rate_hz,
            "chest_wall_ap_mm": self.chest_wall_ap_mm,
            "fiducial_touch_phase_r": (
                None if self.fiducial_touch_phase_r is None else self.fiducial_touch_phase_r.tolist()
            ),
            "fiducial_trace_file": self.fiducial_trace_file,
        }
