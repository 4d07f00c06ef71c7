"""Only what pyproject.toml cannot say: the package list joins the source packages with the
top-level config/ folder, installed as ``robot_defaults`` (setuptools' automatic discovery
does not see a package whose folder has another name)."""

from setuptools import find_packages, setup

setup(packages=find_packages(include=["robot*", "drivers*", "firmware_protocol*"]) + ["robot_defaults"])
