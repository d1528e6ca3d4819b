"""File formats of stereo data: images, PFM, KITTI PNG and EXR depth, Middlebury 2001 ground truth, colour maps."""

from stereo.io.colormap import colorize_disparity
from stereo.io.errors import ArrayFormatError, MalformedFileError, StereoIOError
from stereo.io.exr import read_exr_depth, write_exr_depth
from stereo.io.images import read_grey, read_rgb, write_rgb
from stereo.io.kitti import read_kitti_disparity, write_kitti_disparity
from stereo.io.middlebury import Middlebury2001Info, read_middlebury2001_disparity, read_middlebury2001_info
from stereo.io.pfm import read_pfm, write_pfm

__all__ = [
    "ArrayFormatError",
    "MalformedFileError",
    "Middlebury2001Info",
    "StereoIOError",
    "colorize_disparity",
    "read_exr_depth",
    "read_grey",
    "read_kitti_disparity",
    "read_middlebury2001_disparity",
    "read_middlebury2001_info",
    "read_pfm",
    "read_rgb",
    "write_exr_depth",
    "write_kitti_disparity",
    "write_pfm",
    "write_rgb",
]
