"""Sensor data: the :class:`Sequence` model, validated streams, readers and the simulator."""
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence, Tracks
from flowins.data.streams import GnssStream, ImuStream, PoseStream

__all__ = ["CameraFrames", "GnssStream", "ImuStream", "PinholeCamera", "PoseStream", "Sequence", "Tracks"]
