"""The flowins folder format: one folder per sequence, plain CSV and YAML.

::

    imu.csv          t,ax,ay,az,wx,wy,wz           [s, m/s², rad/s]          (required)
    frames.csv       t,file   (images under frames/)  or  t,index  (frames.mp4)
    tracks.csv       t,track_id,u,v                 [s, -, px, px]
    gnss.csv         t,lat,lon,alt,h_acc,v_acc      [s, deg, deg, m, m, m]
    groundtruth.csv  t,px,py,pz,qw,qx,qy,qz         [s, m, -] (q empty in every row = positions only)
    calibration.yaml camera: {width, height, fx, fy, cx, cy, distortion},
                     imu_to_camera: {rotation, translation} (or its inverse, camera_to_imu)
    camchain-imucam.yaml  Kalibr's calibration (cam0), read in place of calibration.yaml
    metadata.yaml    free-form mapping -> Sequence.metadata

Every CSV has a header row. Floats are written with ``repr`` (the shortest text
that parses back to the same float64), so ``write_folder`` then ``read_folder``
gives bit-identical arrays. See ``docs/sequence_format.md`` for the conventions.

Every error is a ``ValueError`` that names the file, the 1-based line of the
file (``line N``) where there is one, and what was expected. Errors raised by the
stream constructors (which count 0-based data rows) are rewritten to name the
line of the file.
"""

from flowins.data.folder.format import (
    CAMERA_KEYS,
    FILES,
    FRAME_FILE_COLUMNS,
    FRAME_VIDEO_COLUMNS,
    GNSS_COLUMNS,
    GROUNDTRUTH_COLUMNS,
    IMU_COLUMNS,
    TRACK_COLUMNS,
)
from flowins.data.folder.reading import read_calibration, read_folder
from flowins.data.folder.writing import write_folder, write_frame_images

__all__ = ["CAMERA_KEYS", "FILES", "FRAME_FILE_COLUMNS", "FRAME_VIDEO_COLUMNS", "GNSS_COLUMNS", "GROUNDTRUTH_COLUMNS",
           "IMU_COLUMNS", "TRACK_COLUMNS", "read_calibration", "read_folder", "write_folder", "write_frame_images"]
