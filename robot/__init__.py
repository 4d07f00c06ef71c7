"""Plane-map localization controller for a Mecanum robot (application core)."""

__version__ = "0.1.0"
