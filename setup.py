"""Package layout only (metadata and package data are in pyproject.toml): the code under src/ (with the Hydra
search-path plugin, a namespace package), and the Hydra configs kept at the top of the repository in conf/ (the
lightning-hydra-template layout) installed as the package ``difareli.conf``, so every console script finds them
(``pkg://difareli.conf``) wherever the wheel is installed.

Every importable folder is declared, data-only ones too (``difareli.conf.model``, ``difareli.app.static``,
``difareli.estimators.weights``): setuptools warns about a folder Python could import that the list leaves out."""

import warnings

from setuptools import find_namespace_packages, setup
from setuptools.warnings import InformationOnly

# setuptools' notice on every editable install that maps a package outside src/ (here difareli.conf -> conf/):
# "beware of a folder named like the package in the working directory". This src layout has none, and pip
# would print the notice as a warning box in every `pip install -e .`.
warnings.filterwarnings("ignore", message="Editable installation", category=InformationOnly)


def _importable(where: str, prefix: str = "") -> list[str]:
    """The folders under ``where`` whose dotted names Python can import (the checkpoint folders' names cannot)."""
    found = find_namespace_packages(where, exclude=["*__pycache__*"])
    return [prefix + name for name in found if all(part.isidentifier() for part in name.split("."))]


setup(packages=_importable("src") + ["difareli.conf"] + _importable("conf", prefix="difareli.conf."),
      package_dir={"": "src", "difareli.conf": "conf"})
