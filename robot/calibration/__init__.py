"""Calibration against the building: depth scale, camera mounts and wheel odometry from known walls.

``model`` holds what the data is (plane observations in each camera's frame, keyframes, the wheel
angles between them) and the measurement equations; ``collect`` turns localizer results into that
data; ``solver`` is the batch least-squares solve over all of it with the observability of every
parameter; ``output`` is what of a solve a calibration file may hold. Pure numpy: no clock, no
file, no driver (docs/calibration.md).
"""
