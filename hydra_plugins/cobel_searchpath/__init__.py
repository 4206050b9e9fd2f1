"""Hydra search-path plugin: a ``./conf`` folder in the working directory is searched first.

Only applies to cobel's own app (recognised by its built-in config folder being on the search
path), so other Hydra apps in the same environment are untouched. Users add or override tasks,
envs and agents in ``./conf/<group>/NAME.yaml`` without touching the package.

While cobel composes with a user's ``-cd``/``-cp`` folder as the primary one
(``cobelrun.config.builtin_after_main``), it adds the built-in configs after that folder
instead (and no ``./conf``, as ``cobel run -cd`` never searched it).
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class CobelUserConfSearchPath(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        from cobelrun import config
        from cobelrun.config import builtin_conf_dir, user_conf_dir

        try:
            builtin = builtin_conf_dir().resolve()
        except Exception:
            return
        paths = [e.path for e in search_path.get_path()]
        if config.BUILTIN_AFTER_MAIN:  # cobel's composer with a user's -cd/-cp folder
            search_path.append(provider="cobel", path=f"file://{builtin_conf_dir()}")
            return
        ours = any(
            p and Path(p.removeprefix("file://")).resolve() == builtin
            for p in paths
            if not p.startswith("pkg://")
        )
        user = user_conf_dir()
        if not ours or user is None or user.resolve() == builtin:
            return
        url = f"file://{user.resolve()}"
        if url not in paths:
            search_path.prepend(provider="cobel-user", path=url)
