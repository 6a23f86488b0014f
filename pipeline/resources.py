"""Files that ship inside the installed package: the data catalog and the standard workflows.

Both are package data (``data_catalog/*.yaml``, ``workflows/*.yaml``) read through importlib.resources, so every
command works from any working directory and from a wheel installed into a fresh environment. A workflow is named
either by a path to a YAML file or by the name of a packaged workflow (``demo``, ``tiny``, ``map_rebuild``, ...).
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

from pipeline.errors import ConfigError
from pipeline.names import suggest

CATALOG_PACKAGE = "data_catalog"
WORKFLOW_PACKAGE = "workflows"
STANDARD_MAP_WORKFLOW = "map_rebuild"


def _package_dir(package: str) -> Path:
    """The folder of an installed package's data (a real folder for wheel and editable installs)."""
    path = Path(str(resources.files(package)))
    if not path.is_dir():  # pragma: no cover - zip imports are not supported
        raise ConfigError(package, [f"package data folder {path} is not a folder on disk (zip installs are not "
                                    f"supported: install cornermap as a wheel or from source)"])
    return path


def packaged_catalog_dir() -> Path:
    return _package_dir(CATALOG_PACKAGE)


def packaged_workflows() -> dict[str, Path]:
    """Packaged workflow name -> its YAML file."""
    return {p.stem: p for p in sorted(_package_dir(WORKFLOW_PACKAGE).glob("*.yaml"))}


def resolve_workflow(ref: str | Path) -> Path:
    """A workflow file: ``ref`` as a path when such a file exists, else the packaged workflow of that name.

    ``demo``, ``demo.yaml`` and ``workflows/demo.yaml`` (when no such file exists here) all name the packaged
    ``demo``; anything else that is not a file raises a ConfigError listing the packaged names.
    """
    path = Path(ref)
    if path.is_file():
        return path
    packaged = packaged_workflows()
    name = path.name[:-5] if path.name.endswith(".yaml") else path.name
    if name in packaged and (path.parent == Path(".") or path.parent.name == WORKFLOW_PACKAGE):
        return packaged[name]
    raise ConfigError(str(ref), [f"no workflow file {str(ref)!r} (from {Path.cwd()}) and no packaged workflow "
                                 f"named {name!r}{suggest(name, packaged)}; packaged: {', '.join(packaged)}"])
