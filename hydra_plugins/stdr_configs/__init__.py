"""stdr's Hydra search path: the config folders other distributions ship through the `stdr.configs`
entry-point group (stdr.store.config_packages), searched after stdr's own (docs/extending.md,
"Config files from your package")."""
from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class StdrConfigPackages(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        # stdr is imported only when Hydra builds a search path. Hydra finds this plugin wherever a
        # `hydra_plugins` folder is on the path: a process running another stdr (an older checkout
        # on PYTHONPATH beside this one's editable install) has no config_packages, and none of
        # this package's configs, so it is left alone
        try:
            from stdr.store import config_packages
        except ImportError:
            return
        for name, package in config_packages():
            search_path.append(provider=f"stdr.configs:{name}", path=f"pkg://{package}")
