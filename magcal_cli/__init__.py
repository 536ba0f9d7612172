"""magcal: calibrate magnetometers jointly with an IMU from recorded logs."""

from __future__ import annotations

__version__ = "0.1.0"
__all__ = ["__version__"]
