"""modeling: from a CT volume to a heart model in the heart-centric frame.

Segmentation, chest fiducials, surface mesh, the heart-centric frame from
ellipses in 10 mm slabs (paper section 2.2.3) and the model folder.
"""

from modeling.segment import (
    SegmentationError,
    HeartSegmentation,
    segment_heart,
)
from modeling.options import ModelOptions
from modeling.greatvessels import (
    GreatVessels,
    trace_great_vessels,
)
from modeling.build import (
    ModelBuild,
    ModelingWarning,
    build_heart_model,
)
from modeling.fiducials import (
    FiducialError,
    Fiducials,
    find_fiducials,
    order_fiducials,
)
from modeling.labelmap import (
    LabelMapError,
    LabelMap,
    read_label_map,
    mask_on_grid,
)
from modeling.mesh import Mesh, MeshError, check_mesh, transform_mesh
from modeling.mesh_io import read_ply, write_mesh
from modeling.surface import decimate, mask_to_mesh
from modeling.slab_ellipses import SlabEllipse
from modeling.frame import (
    FrameError,
    HeartFrame,
    fit_heart_frame,
    ANTERIOR_LPS,
)
from modeling.vessels import (
    APEX_LAI_LPS,
    VesselTrim,
    base_direction,
    trim_vessel_stubs,
)
from modeling.model import (
    ModelError,
    HeartModel,
    make_heart_model,
    write_model,
    read_model,
    SOURCE_KEYS,
    FORMAT,
    FORMAT_VERSION,
)
from modeling.render import (
    RenderError,
    offscreen_available,
    render_model_png,
    start_offscreen_probe,
)
from modeling.slicer import (
    Markups,
    SlicerFileError,
    read_itk_transform,
    read_markups,
    write_itk_transform,
    write_markups,
)

__all__ = [
    "ModelOptions",
    "APEX_LAI_LPS",
    "ModelingWarning",
    "base_direction",
    "VesselTrim",
    "trim_vessel_stubs",
    "ModelBuild",
    "build_heart_model",
    "ANTERIOR_LPS",
    "FORMAT",
    "FORMAT_VERSION",
    "FiducialError",
    "Fiducials",
    "FrameError",
    "HeartFrame",
    "HeartModel",
    "HeartSegmentation",
    "LabelMap",
    "LabelMapError",
    "Mesh",
    "MeshError",
    "ModelError",
    "RenderError",
    "SOURCE_KEYS",
    "SegmentationError",
    "SlabEllipse",
    "check_mesh",
    "find_fiducials",
    "fit_heart_frame",
    "make_heart_model",
    "mask_on_grid",
    "decimate",
    "mask_to_mesh",
    "offscreen_available",
    "order_fiducials",
    "read_label_map",
    "read_model",
    "read_ply",
    "render_model_png",
    "segment_heart",
    "start_offscreen_probe",
    "GreatVessels",
    "trace_great_vessels",
    "transform_mesh",
    "write_mesh",
    "write_model",
    # 3D Slicer's files (modeling.slicer)
    "Markups",
    "SlicerFileError",
    "read_itk_transform",
    "read_markups",
    "write_itk_transform",
    "write_markups",
]
