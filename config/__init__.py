"""The shipped defaults: robot config, plane maps and paths, installed as ``robot_defaults``.

This folder is data. It is a package only so that an installed robot (a wheel, not a source
tree) finds its default files through the import system instead of the current directory;
``robot.config.defaults`` is the one place that looks here.
"""
