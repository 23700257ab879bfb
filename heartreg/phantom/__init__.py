"""The synthetic beating, breathing chest: the project's ground truth.

It writes real DICOM (a prospectively gated CT study with GE cardiac private
tags and an ECG waveform instance), a real intra-operative session and
``truth.json``.  It imports nothing from ``imaging``, ``modeling`` or
``registration``: it is the independent truth they are tested against.
The names below are imported on first use (:mod:`hrcore.lazy`): the command
line reads :mod:`heartreg.phantom.config` without importing the phantom.
"""

from hrcore.lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "heartreg.phantom.acquisition": ("AcquisitionPlan", "plan_acquisition"),
    "heartreg.phantom.anatomy": ("ChamberHeart",),
    "heartreg.phantom.chest": ("ChestModel", "build_chest"),
    "heartreg.phantom.chest_render": ("render_slice",),
    "heartreg.phantom.config": ("PRESETS", "SIZES", "Anatomy", "PhantomConfig", "make_config"),
    "heartreg.phantom.ct": ("CTStudyExistsError", "CTTruth", "write_ct_study"),
    "heartreg.phantom.generate": ("PhantomError", "heart_from_truth", "make_phantom"),
    "heartreg.phantom.heart": ("AnalyticHeart",),
    "heartreg.phantom.layout": ("make_heart",),
    "heartreg.phantom.navigation": ("NavigationTruth", "write_navigation"),
    "heartreg.phantom.plus": ("write_plus_sequence", "write_plus_session"),
    "heartreg.phantom.session": ("write_session",),
    "heartreg.phantom.session_truth": ("SessionPointTruth", "SessionTruth"),
})

__all__ = [
    "AcquisitionPlan",
    "AnalyticHeart",
    "Anatomy",
    "ChamberHeart",
    "CTStudyExistsError",
    "CTTruth",
    "NavigationTruth",
    "ChestModel",
    "PRESETS",
    "PhantomConfig",
    "PhantomError",
    "SIZES",
    "SessionPointTruth",
    "SessionTruth",
    "build_chest",
    "heart_from_truth",
    "make_config",
    "make_heart",
    "make_phantom",
    "plan_acquisition",
    "render_slice",
    "write_ct_study",
    "write_plus_sequence",
    "write_plus_session",
    "write_navigation",
    "write_session",
]
