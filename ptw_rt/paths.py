"""Where the project's data files live (config, DBC, committed design file)."""

from __future__ import annotations

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = PROJECT_ROOT / "config"
DEFAULT_CONFIG = CONFIG_DIR / "scooter.yaml"
DEFAULT_DESIGN = CONFIG_DIR / "scooter.design.npz"
DEFAULT_DBC = PROJECT_ROOT / "dbc" / "ptw_rt.dbc"
