"""Hydra search-path plugin: a ``conf/`` folder where a difareli command runs extends the shipped configs.

Only difareli's own apps (those whose primary config is ``pkg://difareli.conf``) are touched, and only when the
folder exists (Hydra warns about a search path that is not there). ``DIFARELI_CONFIG_DIR`` names another folder.
"""

from __future__ import annotations

import os
from pathlib import Path

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class DifareliSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        if not any(e.path == "pkg://difareli.conf" for e in search_path.get_path()):
            return
        user = Path(os.environ.get("DIFARELI_CONFIG_DIR") or "conf").resolve()
        from difareli.configs import CONFIG_DIR

        # In the checkout (an editable install) ./conf is the shipped folder itself: searching it twice adds nothing.
        if user.is_dir() and user != CONFIG_DIR.resolve():
            search_path.append(provider="difareli-user", path=f"file://{user}")
