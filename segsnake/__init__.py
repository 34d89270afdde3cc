"""segsnake: segment 3D structures in medical volumes with smooth spline snakes."""

__version__ = "0.1.0"
