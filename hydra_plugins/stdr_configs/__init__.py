"""stdr's Hydra search path: the config folders other distributions ship through the `stdr.configs`
entry-point group (stdr.store.config_packages), searched after stdr's own (docs/extending.md,
"Config files from your package")."""
from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class StdrConfigPackages(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        from stdr.store import config_packages  # stdr is imported only when Hydra builds a search path

        for name, package in config_packages():
            search_path.append(provider=f"stdr.configs:{name}", path=f"pkg://{package}")
