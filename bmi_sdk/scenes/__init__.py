"""Scenes for the forward simulator: linear RGB + range along each ray (metres, NaN unknown).

Sources: the procedural generator (sensor pixel space, the embedded default)
and dataset loaders (NYU Depth V2 labeled, FlyingThings3D, Middlebury 2014)
whose pinhole images are placed on the curved sensor by :mod:`placement`.
Conventions and metric-depth rules: ``docs/scenes.md``.
"""

from bmi_sdk.scenes.flyingthings import FlyingThings3D, disparity_to_z_m, flyingthings_intrinsics
from bmi_sdk.scenes.middlebury import Middlebury2014, load_middlebury_scene, read_middlebury_calib
from bmi_sdk.scenes.nyu import NYU_RGB_INTRINSICS, NyuDepthV2, read_nyu_split
from bmi_sdk.scenes.pfm import PfmError, read_pfm, write_pfm
from bmi_sdk.scenes.placement import (
                                      PatchMapping,
                                      PlacedScene,
                                      corner_phi_deg,
                                      place_patch,
                                      place_wide,
                                      resample_to_sensor,
                                      tan_vs_angle_relative_error,
)
from bmi_sdk.scenes.procedural import generate_scene
from bmi_sdk.scenes.scene import PinholeIntrinsics, Scene

__all__ = [
    "Scene", "PinholeIntrinsics", "generate_scene",
    "NyuDepthV2", "NYU_RGB_INTRINSICS", "read_nyu_split",
    "FlyingThings3D", "flyingthings_intrinsics", "disparity_to_z_m",
    "Middlebury2014", "load_middlebury_scene", "read_middlebury_calib",
    "place_patch", "place_wide", "PatchMapping", "PlacedScene", "resample_to_sensor", "corner_phi_deg",
    "tan_vs_angle_relative_error",
    "read_pfm", "write_pfm", "PfmError",
]
