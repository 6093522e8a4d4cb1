"""Where the project's own resources live (``config/``, ``static/``)."""

from __future__ import annotations

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = PROJECT_ROOT / "config"
STATIC_DIR = PROJECT_ROOT / "static"
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"
RIGS_DIR = CONFIG_DIR / "rigs"
SCENARIOS_DIR = CONFIG_DIR / "scenarios"
MODELS_DIR = CONFIG_DIR / "models"
