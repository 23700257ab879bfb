"""modeling: from a CT volume to a heart model in the heart-centric frame.

Segmentation, chest fiducials, surface mesh, the heart-centric frame from
ellipses in 10 mm slabs (paper section 2.2.3) and the model folder. The names
below are what a caller needs: build a model (:func:`build_heart_model` with
:class:`ModelOptions`), write and read it back, and the stages it is made of;
file formats, 3D Slicer files and helpers stay importable from their modules.
"""

from modeling.build import ModelBuild, build_heart_model
from modeling.fiducials import FiducialError, find_fiducials
from modeling.frame import FrameError, HeartFrame, fit_heart_frame
from modeling.mesh import Mesh, MeshError
from modeling.model import HeartModel, ModelError, make_heart_model, read_model, write_model
from modeling.options import ModelOptions
from modeling.render import offscreen_available, render_model_png
from modeling.segment import SegmentationError, segment_heart
from modeling.surface import mask_to_mesh

__all__ = [
    # a model
    "ModelOptions",
    "ModelBuild",
    "build_heart_model",
    "HeartModel",
    "make_heart_model",
    "read_model",
    "write_model",
    "render_model_png",
    "offscreen_available",
    # its stages
    "segment_heart",
    "find_fiducials",
    "Mesh",
    "mask_to_mesh",
    "HeartFrame",
    "fit_heart_frame",
    # refusals (each a hrcore.HeartregError)
    "ModelError",
    "SegmentationError",
    "FiducialError",
    "MeshError",
    "FrameError",
]
