"""Where things are in the phantom's chest (CT patient frame, LPS, mm).

Shared by the CT renderer and the session generator so that both see the same
body, fiducials and reference probe.  LPS: +x patient left, +y posterior,
+z superior; so the anterior chest wall is at negative y.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from heartreg.phantom.config import PhantomConfig
from heartreg.phantom.heart import AnalyticHeart, T_from_euler_xyz_deg

__all__ = [
    "BODY_SEMI_LR_MM",
    "BODY_SEMI_AP_MM",
    "FIDUCIAL_SPACING_MM",
    "FIDUCIAL_SIZE_MM",
    "STERNUM_MID_Z_MM",
    "skin_y_mm",
    "fiducials_patient_mm",
    "T_patient_from_probe",
    "T_fiducial_shift",
    "make_heart",
]

#: body outline: an ellipse in every axial plane, centred on x = y = 0.
BODY_SEMI_LR_MM = 115.0
BODY_SEMI_AP_MM = 95.0
#: 3 x 3 grid of skin staples, 4 cm apart, centred mid-sternum.
FIDUCIAL_SPACING_MM = 40.0
#: staple footprint (left-right, superior-inferior) and thickness, mm.
FIDUCIAL_SIZE_MM = (6.5, 4.7, 1.6)
STERNUM_MID_Z_MM = 10.0


def skin_y_mm(x_mm) -> np.ndarray:
    """Anterior skin surface y (mm, negative) at left-right position x."""
    x = np.clip(np.asarray(x_mm, dtype=float) / BODY_SEMI_LR_MM, -1.0, 1.0)
    return -BODY_SEMI_AP_MM * np.sqrt(1.0 - x**2)


def fiducials_patient_mm() -> np.ndarray:
    """Centres of the 9 skin fiducials, (9, 3) mm, in the documented order.

    Order: rows from superior to inferior, within a row from patient right to
    patient left (increasing x), i.e. row-major from the superior-right staple.
    Each staple lies on the skin; its centre is half its thickness outside.
    """
    rows = STERNUM_MID_Z_MM + FIDUCIAL_SPACING_MM * np.array([1.0, 0.0, -1.0])
    cols = FIDUCIAL_SPACING_MM * np.array([-1.0, 0.0, 1.0])
    z, x = np.meshgrid(rows, cols, indexing="ij")
    x, z = x.ravel(), z.ravel()
    y = skin_y_mm(x) - 0.5 * FIDUCIAL_SIZE_MM[2]
    return np.stack([x, y, z], axis=1)


def T_patient_from_probe() -> np.ndarray:
    """Ground-truth placement T* of the reference probe on the chest at the image
    phase: on the right lower anterior chest wall, z out of the chest (anterior),
    x towards the patient's left, tilted 12 degrees."""
    x_axis = np.array([1.0, 0.0, 0.0])
    z_axis = np.array([0.0, -1.0, 0.0])
    R = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
    tilt = Rotation.from_euler("xyz", [12.0, -8.0, 15.0], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R @ tilt
    x0 = -70.0
    T[:3, 3] = [x0, skin_y_mm(x0) - 2.0, -45.0]
    return T


def T_fiducial_shift(config: PhantomConfig) -> np.ndarray:
    """Systematic CT-to-surgery motion of the skin relative to the heart.

    A rigid transform in the patient frame: a rotation of
    ``config.fiducial_shift_deg`` about the heart's origin, then a translation of
    ``config.fiducial_shift_mm``.  The staples as found in surgery are
    ``T_fiducial_shift @ f_ct``, so the fiducial registration
    ``T0 = inv(T_fiducial_shift) @ T*`` misplaces the heart's centre by exactly
    ``-R^T fiducial_shift_mm``: the preset's shift vector is the error the
    paper's empirical metric (eq. 10) sees at the heart.
    """
    centre = np.asarray(config.heart_origin_mm, dtype=float)
    R = Rotation.from_euler("xyz", config.fiducial_shift_deg, degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + np.asarray(config.fiducial_shift_mm)
    return T


def make_heart(config: PhantomConfig) -> AnalyticHeart:
    """The analytic heart of ``config``, placed in the CT patient frame
    (a :class:`~heartreg.phantom.anatomy.ChamberHeart` when
    ``config.anatomy.heart == "chambers"``)."""
    from heartreg.phantom.anatomy import ChamberHeart

    cls = ChamberHeart if config.anatomy.heart == "chambers" else AnalyticHeart
    heart = cls(
        shape=config.heart,
        motion=config.motion,
        T_patient_from_heart=T_from_euler_xyz_deg(config.euler_xyz_deg, config.heart_origin_mm),
        image_resp_phase=config.image_resp_phase,
    )
    if cls is ChamberHeart:
        # the epicardium without the great vessels ends at the arteries' valves (anatomy's module docstring)
        from heartreg.phantom.great_vessels import arterial_roots, great_vessels

        phase_c = config.gating_target_phase
        heart = replace(heart, roots=arterial_roots(heart, great_vessels(heart, phase_c=phase_c), phase_c))
    return heart
