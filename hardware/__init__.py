"""ringscan.hardware."""

from .camera import CameraDevice, FolderCamera, OpenCVCamera, SocketCamera, VirtualCamera, make_virtual_rig, open_camera
from .capture import CaptureSettings, capture_scan, plan_angles, read_capture_state, resume_angle
from .errors import (
    CameraError,
    CaptureError,
    DeviceDisconnected,
    DeviceError,
    DeviceTimeout,
    ProjectorCommandError,
    ProjectorDisconnected,
    ProjectorError,
    ProjectorTimeout,
    TurntableAlarm,
    TurntableCommandError,
    TurntableDisconnected,
    TurntableError,
    TurntableTimeout,
)
from .projector import ProjectorDevice, SerialProjector, VirtualProjector
from .turntable import GrblTurntable, TurntableDevice, VirtualTurntable

__all__ = [
    "CameraDevice", "OpenCVCamera", "FolderCamera", "VirtualCamera", "SocketCamera", "open_camera",
    "make_virtual_rig",
    "ProjectorDevice", "SerialProjector", "VirtualProjector",
    "TurntableDevice", "GrblTurntable", "VirtualTurntable",
    "CaptureSettings", "capture_scan", "plan_angles", "read_capture_state", "resume_angle",
    "DeviceError", "DeviceTimeout", "DeviceDisconnected",
    "TurntableError", "TurntableAlarm", "TurntableCommandError", "TurntableTimeout", "TurntableDisconnected",
    "ProjectorError", "ProjectorCommandError", "ProjectorTimeout", "ProjectorDisconnected",
    "CameraError", "CaptureError",
]
