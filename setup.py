"""The package list and folders, which pyproject.toml cannot say: the device, mock, replay and
simulation code lives in top-level folders (drivers/, mock_devices/, hil/, simulation/, as the
project brief lays it out) but installs only inside the one import name ``u2sa_hw``, so nothing
generic (``drivers``, ``simulation``) lands in site-packages (docs/architecture.md)."""

from setuptools import find_namespace_packages, setup

#: import name -> folder. Each folder's __init__.py refuses any other name.
FOLDERS = {
    "u2sa_hw.drivers": "drivers",
    "u2sa_hw.mocks": "mock_devices",
    "u2sa_hw.hil": "hil",
    "u2sa_hw.simulation": "simulation",
}

# Namespace discovery: a folder of modules is a package even before it has an __init__.py, so a new
# device family is never left out of the wheel while it works from the source tree.
NOT_CODE = ["*__pycache__*", "*.egg-info*"]
packages = find_namespace_packages(include=["u2sa_hw", "u2sa_hw.*"], exclude=NOT_CODE)
for name, folder in FOLDERS.items():
    packages += [name] + [f"{name}.{sub}" for sub in find_namespace_packages(folder, exclude=NOT_CODE)]

setup(packages=packages, package_dir=FOLDERS)
