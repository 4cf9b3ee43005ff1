"""Emulators of the rig's devices behind pseudo-terminals and a socket.

``ringscan emulate`` and the tests drive the real drivers against them: a GRBL 1.1
turntable (:mod:`.grbl`: whole motor steps, WCO in only some status reports,
ALARM:3 on a reset in motion, "Reset to continue" after a limit alarm, feed hold,
the ``$110`` rate cap), the serial pattern projector (:mod:`.projector`) and a
camera server (:mod:`.rig`) around the virtual camera (:mod:`.virtual`), which
renders with the virtual rig. They behave like the devices' documentation and
firmware, faults included (:class:`Fault`).
"""

from ringscan.hardware.emulators.grbl import EmulatedTurntable
from ringscan.hardware.emulators.projector import EmulatedProjector
from ringscan.hardware.emulators.pty_device import FAULT_KINDS, Fault
from ringscan.hardware.emulators.rig import CameraServer, EmulatedRig
from ringscan.hardware.emulators.virtual import VirtualCamera, make_virtual_rig

__all__ = ["EmulatedTurntable", "EmulatedProjector", "Fault", "FAULT_KINDS", "CameraServer", "EmulatedRig",
           "VirtualCamera", "make_virtual_rig"]
