"""The flowins folder format's names: its files, their columns and keys, and bounds."""
from __future__ import annotations

from flowins.data.kalibr import CAMCHAIN

IMU_COLUMNS = ("t", "ax", "ay", "az", "wx", "wy", "wz")
FRAME_FILE_COLUMNS = ("t", "file")
FRAME_VIDEO_COLUMNS = ("t", "index")
TRACK_COLUMNS = ("t", "track_id", "u", "v")
GNSS_COLUMNS = ("t", "lat", "lon", "alt", "h_acc", "v_acc")
GROUNDTRUTH_COLUMNS = ("t", "px", "py", "pz", "qw", "qx", "qy", "qz")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")
EXTRINSIC_KEYS = ("rotation", "translation")
EXTRINSIC_NAMES = ("imu_to_camera", "camera_to_imu")
#: Largest disagreement allowed between ``imu_to_camera`` and the inverse of ``camera_to_imu``
#: when a calibration.yaml gives both: far below any calibration's accuracy (about 1e-3 rad and
#: 1e-3 m), above the rounding of numbers printed with six decimals.
EXTRINSIC_AGREEMENT_RAD = 1e-5
EXTRINSIC_AGREEMENT_M = 1e-5

#: Every name the format owns inside a sequence folder.
FILES = (
    "imu.csv",
    "frames.csv",
    "frames",
    "frames.mp4",
    "tracks.csv",
    "gnss.csv",
    "groundtruth.csv",
    "calibration.yaml",
    CAMCHAIN,
    "metadata.yaml",
)

# Plausibility bounds of the IMU units (medians over the whole file).
_ACC_MEDIAN_MIN_MPS2 = 2.0
_ACC_MEDIAN_MAX_MPS2 = 50.0
_GYRO_MEDIAN_MAX_RPS = 20.0
# A quaternion read from a file whose norm is this close to 1 is kept bit-for-bit.
_UNIT_NORM_TOL = 1e-15
