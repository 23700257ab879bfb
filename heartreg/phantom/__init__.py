"""The synthetic beating, breathing chest: the project's ground truth.

It writes real DICOM (a prospectively gated CT study with GE cardiac private
tags and an ECG waveform instance), a real intra-operative session and
``truth.json``.  It imports nothing from ``imaging``, ``modeling`` or
``registration``: it is the independent truth they are tested against.
"""

from heartreg.phantom.acquisition import AcquisitionPlan, plan_acquisition
from heartreg.phantom.anatomy import ChamberHeart
from heartreg.phantom.chest import ChestModel, build_chest
from heartreg.phantom.chest_render import render_slice
from heartreg.phantom.config import PRESETS, SIZES, Anatomy, PhantomConfig, make_config
from heartreg.phantom.ct import CTStudyExistsError, CTTruth, write_ct_study
from heartreg.phantom.generate import PhantomError, heart_from_truth, make_phantom
from heartreg.phantom.heart import AnalyticHeart
from heartreg.phantom.layout import make_heart
from heartreg.phantom.navigation import NavigationTruth, write_navigation
from heartreg.phantom.plus import write_plus_sequence, write_plus_session
from heartreg.phantom.session import write_session
from heartreg.phantom.session_truth import SessionPointTruth, SessionTruth

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
