"""ringscan.hardware."""

from ringscan.hardware.capture.sequence import (
    CaptureSettings,
    capture_scan,
    plan_angles,
    read_capture_state,
    resume_angle,
)
from ringscan.hardware.devices.camera import CameraDevice, FolderCamera, OpenCVCamera, SocketCamera, open_camera
from ringscan.hardware.devices.grbl import GrblTurntable
from ringscan.hardware.devices.projector import ProjectorDevice, SerialProjector, VirtualProjector
from ringscan.hardware.devices.turntable import TurntableDevice, VirtualTurntable
from ringscan.hardware.emulators.virtual import VirtualCamera, make_virtual_rig
from ringscan.hardware.errors import (
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
