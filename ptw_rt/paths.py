"""Where the project's data files live (config, DBC, committed design file)."""

from __future__ import annotations

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = PROJECT_ROOT / "config"
DEFAULT_CONFIG = CONFIG_DIR / "scooter.yaml"
DEFAULT_DESIGN = CONFIG_DIR / "scooter.design.npz"
DEFAULT_DBC = PROJECT_ROOT / "dbc" / "ptw_rt.dbc"


def own_design_file(config: str | Path) -> Path:
    """The design file of a configuration: its name with ``.design.npz``, beside it (``config/scooter.yaml`` ->
    ``config/scooter.design.npz``). `ptw-rt design --config C` writes it by default, so designing for a vehicle file
    of one's own (a rider's `added_mass`) never overwrites the shipped design another file relies on."""
    c = Path(config)
    return c.with_name(c.stem + ".design.npz")


def design_file_for(config: str | Path) -> Path:
    """The design file a command reads when none is named: the configuration's own (`own_design_file`) if it
    exists, else the shipped one (a copy of the shipped file, or one that changes only ``runtime:``, needs no
    design of its own: the design file's config hash says whether it fits)."""
    own = own_design_file(config)
    return own if own.is_file() else DEFAULT_DESIGN
