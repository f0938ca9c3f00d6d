"""Sensor data: validated, immutable streams (IMU, GNSS, reference poses)."""
from flowins.data.streams import GnssStream, ImuStream, PoseStream

__all__ = ["GnssStream", "ImuStream", "PoseStream"]
