"""registration: spatiotemporal registration of an organ-mounted robot to the heart model.

Session reading, AM Fourier motion models (paper section 2.2.5), fiducial
registration, ICP to the surface, the respiration-phase sweep with the
paper's empirical metric (section 2.3) and the registration's outputs. The
names below are what a caller needs: read a session, register it
(:func:`register_session` with :class:`RegistrationOptions`) and write the
result, or run one stage of it; file formats, ICP internals and the 4x4
helpers (:mod:`hrcore.geometry`) stay importable from their modules.
"""

from registration.fiducial import FiducialRegistration, register_fiducials
from registration.localise import Localiser
from registration.motion_model import Harmonics, MotionModel, fit_motion_model
from registration.online import CausalPhases
from registration.options import RegistrationOptions
from registration.pipeline import RegistrationError, register_session
from registration.plus import PlusSequence, read_plus_sequence
from registration.report import RegistrationFileError, read_registration, write_registration
from registration.result import RegistrationResult
from registration.session import Session, SessionError, read_session
from registration.spatiotemporal import SpatiotemporalRegistration, register_spatiotemporal
from registration.transforms import rotation_distance_deg, translation_distance_mm
from registration.view import render_registration_png

__all__ = [
    # a registration
    "RegistrationOptions",
    "Session",
    "read_session",
    "register_session",
    "RegistrationResult",
    "read_registration",
    "write_registration",
    "render_registration_png",
    # its stages
    "FiducialRegistration",
    "register_fiducials",
    "Harmonics",
    "MotionModel",
    "fit_motion_model",
    "SpatiotemporalRegistration",
    "register_spatiotemporal",
    # live localisation and PLUS recordings
    "CausalPhases",
    "Localiser",
    "PlusSequence",
    "read_plus_sequence",
    # comparing poses
    "rotation_distance_deg",
    "translation_distance_mm",
    # refusals (each a hrcore.HeartregError)
    "RegistrationError",
    "RegistrationFileError",
    "SessionError",
]
