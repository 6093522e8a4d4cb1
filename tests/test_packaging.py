"""A non-editable install (``pip install .``) has what the commands need: every package, and
config/ as the data package ``trackmeter._config``, which ``trackmeter.paths`` falls back to."""

from __future__ import annotations

import importlib.util
import shutil
import tomllib
from pathlib import Path

import pytest

import trackmeter.paths

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def setuptools_config() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def test_every_package_is_listed(setuptools_config: dict) -> None:
    """The package list is explicit (for the config/ mapping): a new subpackage must join it,
    or a wheel would ship without it."""
    found = {
        ".".join(init.parent.relative_to(REPO).parts)
        for top in ("trackmeter", "console")
        for init in (REPO / top).rglob("__init__.py")
    }
    assert set(setuptools_config["packages"]) == found | {"trackmeter._config"}


def test_every_config_file_is_package_data(setuptools_config: dict) -> None:
    assert setuptools_config["package-dir"]["trackmeter._config"] == "config"
    patterns = setuptools_config["package-data"]["trackmeter._config"]
    shipped = {p for pattern in patterns for p in (REPO / "config").glob(pattern) if p.is_file()}
    assert shipped == {p for p in (REPO / "config").rglob("*") if p.is_file()}


def _paths_module_at(package_dir: Path):  # type: ignore[no-untyped-def]
    """``trackmeter/paths.py`` loaded as if it lived in ``package_dir``."""
    package_dir.mkdir(parents=True, exist_ok=True)
    shutil.copy(trackmeter.paths.__file__, package_dir / "paths.py")
    spec = importlib.util.spec_from_file_location("paths_under_test", package_dir / "paths.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def test_source_tree_config_first() -> None:
    assert trackmeter.paths.CONFIG_DIR == REPO / "config"
    assert trackmeter.paths.DEFAULT_CONFIG == REPO / "config" / "default.yaml"


def test_installed_package_uses_its_packaged_config(tmp_path: Path) -> None:
    """Installed: site-packages/trackmeter/_config, even beside someone else's top-level
    config/ (site-packages is no source tree)."""
    site = tmp_path / "site-packages"
    shutil.copytree(REPO / "config", site / "trackmeter" / "_config")
    (site / "config").mkdir()
    (site / "config" / "default.yaml").write_text("not: ours\n")
    paths = _paths_module_at(site / "trackmeter")
    assert paths.CONFIG_DIR == site / "trackmeter" / "_config"
    assert paths.DEFAULT_CONFIG.is_file() and (paths.SCENARIOS_DIR / "estec.yaml").is_file()
    assert (paths.RIGS_DIR / "estec_12mm.yaml").is_file() and (paths.MODELS_DIR / "estec_mockup.yaml").is_file()
