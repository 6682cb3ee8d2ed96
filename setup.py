"""The package list and folders, which pyproject.toml cannot say: the device, mock, replay and
simulation code lives in top-level folders (drivers/, mock_devices/, hil/, simulation/, as the
project brief lays it out) but installs only inside the one import name ``u2sa_hw``, so nothing
generic (``drivers``, ``simulation``) lands in site-packages (docs/architecture.md)."""

from setuptools import find_packages, setup

#: import name -> folder. Each folder's __init__.py refuses any other name.
FOLDERS = {
    "u2sa_hw.drivers": "drivers",
    "u2sa_hw.mocks": "mock_devices",
    "u2sa_hw.hil": "hil",
    "u2sa_hw.simulation": "simulation",
}

packages = find_packages(include=["u2sa_hw", "u2sa_hw.*"])
for name, folder in FOLDERS.items():
    packages += [name] + [f"{name}.{sub}" for sub in find_packages(folder)]

setup(packages=packages, package_dir=FOLDERS)
