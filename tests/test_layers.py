"""The package's layers: no module imports from a layer above its own (lazy imports inside functions included).

The order, lowest first, is the one README's layout section describes: the jitted core knows nothing of CAN,
the I/O edge nothing of the service around it, the service nothing of the applications built on it.
"""

from __future__ import annotations

import ast

import pytest

from ptw_rt.paths import PROJECT_ROOT

PACKAGE = PROJECT_ROOT / "ptw_rt"

# lowest first; the names of one layer may import each other
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "errors",
        "paths",
        "output",
        "untrusted",
        "schema",
        "_numba_cache",
        "_deferred_imports",
        "progress",
        "parallel",
    ),  # shared plumbing: no project imports beyond these
    ("model",),  # vehicle parameters, Sharp's matrices
    ("settings",),  # the typed config file
    ("analysis",),  # zeros, modes (offline)
    ("design",),  # observer design (offline), the design file
    ("core",),  # the jitted estimator step
    ("io",),  # DBC codec, E2E, candump logs, NMEA, state file
    ("sim",),  # plant, rider, sensors, recorded rides
    ("edge",),  # frames in -> Sample -> step -> frames out
    ("service",),  # the daemon: loop, real time, sd_notify, logs
    ("eval",),  # scoring against truth, baselines, plots
    ("apps",),  # demo, replay, monitor, bench
    ("cli", "__main__"),
)
LAYER_OF = {name: k for k, names in enumerate(LAYERS) for name in names}


def _component(module: str) -> str:
    """``ptw_rt.edge.cycle`` -> ``edge``."""
    return module.split(".")[1]


def _module_name(path) -> str:
    rel = path.relative_to(PROJECT_ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_imports(path) -> list[tuple[int, str]]:
    """(line, imported ptw_rt module) of every import statement in the file, wherever it stands."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    this = _module_name(path)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("ptw_rt.")]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:  # relative import: resolve against this module's package
                base = this.split(".")[: -node.level] if not path.name == "__init__.py" else this.split(".")
                module = ".".join([*base, module] if module else base)
            if module == "ptw_rt":  # from ptw_rt import edge
                found += [(node.lineno, f"ptw_rt.{a.name}") for a in node.names]
            elif module.startswith("ptw_rt."):
                found.append((node.lineno, module))
    return found


def _sources():
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_component_has_a_layer():
    components = {_component(_module_name(p)) for p in _sources() if _module_name(p) != "ptw_rt"}
    assert components <= set(LAYER_OF), f"not in LAYERS: {sorted(components - set(LAYER_OF))}"


@pytest.mark.parametrize("path", _sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_upward_import(path):
    module = _module_name(path)
    if module == "ptw_rt":
        return
    own = LAYER_OF[_component(module)]
    upward = [
        f"line {line}: {target} (layer {LAYER_OF[_component(target)]} > {own})"
        for line, target in project_imports(path)
        if LAYER_OF.get(_component(target), -1) > own
    ]
    assert not upward, f"{module} imports from a higher layer: " + "; ".join(upward)


def test_the_check_catches_an_upward_import(tmp_path, monkeypatch):
    """The checker itself: a core module importing the daemon is reported."""
    fake_root = tmp_path
    (fake_root / "ptw_rt" / "core").mkdir(parents=True)
    bad = fake_root / "ptw_rt" / "core" / "bad.py"
    bad.write_text("def f():\n    from ptw_rt.service.daemon import Daemon\n    return Daemon\n")
    monkeypatch.setattr(__import__(__name__), "PROJECT_ROOT", fake_root)
    assert project_imports(bad) == [(2, "ptw_rt.service.daemon")]
    with pytest.raises(AssertionError, match="higher layer"):
        test_no_upward_import(bad)


def test_settings_do_not_load_the_real_time_code():
    """`ptw-rt design` and friends read the config file without the daemon's ctypes scheduler code."""
    import subprocess
    import sys

    code = "import sys, ptw_rt.settings; print(sorted(m for m in sys.modules if m.startswith('ptw_rt.')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "ptw_rt.service" not in out and "ptw_rt.edge" not in out, out
