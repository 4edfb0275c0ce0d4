"""bmi-sdk: optics, simulation and reconstruction for the monocentric RGBD camera."""

__version__ = "0.1.0"
