"""Package layout only (metadata is in pyproject.toml): the code under src/ (with the Hydra search-path plugin,
a namespace package), and the Hydra configs kept at the top of the repository in conf/ (the lightning-hydra-template
layout) installed as the package ``difareli.conf``, so every console script finds them (``pkg://difareli.conf``)
wherever the wheel is installed."""

from setuptools import find_namespace_packages, find_packages, setup

setup(packages=find_packages("src") + find_namespace_packages("src", include=["hydra_plugins*"]) + ["difareli.conf"],
      package_dir={"": "src", "difareli.conf": "conf"})
