"""registration: spatiotemporal registration of an organ-mounted robot to the heart model.

Session reading, AM Fourier motion models (paper section 2.2.5), fiducial
registration, ICP to the surface, the respiration-phase sweep with the
paper's empirical metric (section 2.3) and the registration's outputs. The
names below are what a caller needs: read a session, register it
(:func:`register_session` with :class:`RegistrationOptions`) and write the
result, or run one stage of it; file formats, ICP internals and the 4x4
helpers (:mod:`hrcore.geometry`) stay importable from their modules.
The names are imported on first use (:mod:`hrcore.lazy`): reading
:mod:`registration.options` (the command line's defaults) imports nothing else.
"""

from hrcore.lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "registration.fiducial": ("FiducialRegistration", "register_fiducials"),
    "registration.localise": ("Localiser",),
    "registration.motion_model": ("Harmonics", "MotionModel", "fit_motion_model"),
    "registration.online": ("CausalPhases",),
    "registration.options": ("RegistrationOptions",),
    "registration.pipeline": ("RegistrationError", "register_session"),
    "registration.plus": ("PlusSequence", "read_plus_sequence"),
    "registration.report": ("RegistrationFileError", "read_registration", "write_registration"),
    "registration.result": ("RegistrationResult",),
    "registration.session": ("Session", "SessionError", "read_session"),
    "registration.spatiotemporal": ("SpatiotemporalRegistration", "register_spatiotemporal"),
    "registration.transforms": ("rotation_distance_deg", "translation_distance_mm"),
    "registration.view": ("render_registration_png",),
})

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
