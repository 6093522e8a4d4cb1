"""Where the project's own resources live (``config/``).

``config/`` sits at the top of the repository (DESIGN.md names ``config/default.yaml``). A
checkout or an editable install reads it there, so an edit takes effect at once; a wheel
(``pip install .``) has no source tree and carries a copy as the data package
``trackmeter._config`` (see ``pyproject.toml``), used when the source tree's is absent.
"""

from __future__ import annotations

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
_SOURCE_CONFIG_DIR = PROJECT_ROOT / "config"
_PACKAGED_CONFIG_DIR = Path(__file__).resolve().parent / "_config"


def _config_dir() -> Path:
    # The source tree only when PROJECT_ROOT is one (pyproject.toml beside config/): installed,
    # PROJECT_ROOT is site-packages, where some other distribution's "config" could sit.
    if (PROJECT_ROOT / "pyproject.toml").is_file() and (_SOURCE_CONFIG_DIR / "default.yaml").is_file():
        return _SOURCE_CONFIG_DIR
    if (_PACKAGED_CONFIG_DIR / "default.yaml").is_file():
        return _PACKAGED_CONFIG_DIR
    return _SOURCE_CONFIG_DIR  # neither: errors name the path DESIGN.md documents


CONFIG_DIR = _config_dir()
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"
RIGS_DIR = CONFIG_DIR / "rigs"
SCENARIOS_DIR = CONFIG_DIR / "scenarios"
MODELS_DIR = CONFIG_DIR / "models"


def preset(name_or_path: str | Path, folder: Path) -> Path | None:
    """``name_or_path`` as a preset in ``folder`` (``NAME`` or ``NAME.yaml``, e.g. a scenario or
    a rig named on the command line): that file when ``name_or_path`` is a bare name that is
    not itself a file here and the preset exists, else None."""
    p = Path(name_or_path)
    if p.is_file() or p.parent != Path("."):
        return None
    return next((c for c in (folder / p.name, folder / f"{p.name}.yaml") if c.is_file()), None)


def preset_names(folder: Path) -> list[str]:
    """The presets of ``folder`` (its ``*.yaml`` files' names), sorted."""
    return sorted(f.stem for f in folder.glob("*.yaml"))
