"""What every device of the rig has in common: recover after a fault, close, and
use as a context manager (``with open_camera(...) as cam:``)."""

from __future__ import annotations

import abc

__all__ = ["Device"]


class Device(abc.ABC):
    """Base of cameras, projectors and turntables."""

    def recover(self) -> None:
        """Bring the device back after a fault (reconnect, resynchronise); the
        default does nothing."""

    def close(self) -> None:
        """Release the device; the default does nothing."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
