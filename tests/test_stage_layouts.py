"""The stages' declarations: layouts match their named constants, parameters build, the buffers pack, and a
stage imports only the stages that run before it (so the data flow is what `STAGES` says)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil

import numpy as np
import pytest
from numba import njit

from ptw_rt import core
from ptw_rt.core import estimator as E  # noqa: N812
from ptw_rt.core.stage import Layout, borrowed, pack, v1, v2, v3
from ptw_rt.paths import PROJECT_ROOT


def _module_of(stage):
    """The ptw_rt.core module whose STAGE it is (a new stage module is found without listing it here)."""
    for info in pkgutil.iter_modules(core.__path__):
        mod = importlib.import_module(f"ptw_rt.core.{info.name}")
        if getattr(mod, "STAGE", None) is stage:
            return mod
    raise AssertionError(f"no module holds stage {stage.name}")


STAGE_MODULES = [(s.name, _module_of(s)) for s in E.STAGES]


@pytest.mark.parametrize(("name", "mod"), STAGE_MODULES, ids=[n for n, _ in STAGE_MODULES])
def test_every_layout_constant_is_its_table_entry(name, mod):
    stage = mod.STAGE
    for layout in (stage.state, stage.params, stage.outputs):
        assert layout.size == sum(size for _, size in layout.fields)
        for const, (field, _size) in zip(layout.constant_names(), layout.fields, strict=True):
            assert getattr(mod, const) == layout.offset[field], f"{mod.__name__}.{const} is not field {field}"
    for k, (table, _) in enumerate(stage.tables):
        consts = [c for c in dir(mod) if c.startswith("T_") and getattr(mod, c) == k]
        assert consts, f"{mod.__name__}: no T_ constant for table {k} ({table})"


@pytest.mark.parametrize(("name", "mod"), STAGE_MODULES, ids=[n for n, _ in STAGE_MODULES])
def test_parameters_state_and_tables_build_from_the_default_config(name, mod, settings, design):
    stage = mod.STAGE
    b = stage.alone(settings, design)
    assert b.params.shape == (stage.params.size,) and np.all(np.isfinite(b.params))
    assert b.state.size >= stage.state.size and b.outputs.shape == (stage.outputs.size,)
    assert len(b.tindex) == len(stage.tables)
    assert stage.doc


def test_a_stage_imports_only_stages_that_run_before_it():
    order = {name: k for k, name in enumerate(E.STAGE_NAMES)}
    module_stage = {mod.__name__: name for name, mod in STAGE_MODULES}
    for name, mod in STAGE_MODULES:
        tree = ast.parse(inspect.getsource(mod))
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for t in targets:
                other = module_stage.get(t)
                if other is not None and other != name:
                    assert order[other] < order[name], f"stage {name} imports {other}, which runs after it"


def test_no_core_module_imports_the_estimator():
    """`core/estimator.py` is the top of the core: nothing below imports it (the old params <-> estimator cycle)."""
    for path in sorted((PROJECT_ROOT / "ptw_rt" / "core").glob("*.py")):
        if path.name == "estimator.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert "ptw_rt.core.estimator" not in names, f"{path.name} imports the estimator"


def test_layout_vector_fills_by_name_and_refuses_gaps():
    lay = Layout("X_", a=1, b=3, c=1)
    assert lay.offsets == (0, 1, 4) and lay.size == 5
    assert lay.constant_names() == ("X_A", "X_B", "X_C")
    np.testing.assert_array_equal(lay.vector(a=1.0, b=[2.0, 3.0, 4.0], c=5.0), [1, 2, 3, 4, 5])
    with pytest.raises(KeyError, match="not given"):
        lay.vector(a=1.0, b=0.0)
    with pytest.raises(KeyError, match="not in the layout"):
        lay.vector(a=1.0, b=0.0, c=0.0, d=1.0)
    np.testing.assert_array_equal(lay.vector({"c": 2.0}, strict=False), [0, 0, 0, 0, 2])
    assert lay.describe() == "a, b[3], c"
    with pytest.raises(ValueError):
        Layout("Y_", a=0)


def test_pack_and_views_round_trip():
    a, b, c = np.arange(3.0), np.arange(6.0).reshape(2, 3), np.arange(24.0).reshape(2, 3, 4)
    buf, index = pack([a, b, c])
    np.testing.assert_array_equal(v1(buf, index, 0), a)
    np.testing.assert_array_equal(v2(buf, index, 1), b)
    np.testing.assert_array_equal(v3(buf, index, 2), c)


@njit
def _compiled_views(buf, index, src):
    got = (v1(buf, index, 0).copy(), v2(buf, index, 1).copy(), v3(buf, index, 2).copy(), borrowed(src).copy())
    v3(buf, index, 2)[1, 2, 3] = -1.0  # a view, not a copy
    return got


def test_compiled_views_round_trip():
    """Compiled, the views and `borrowed` are carrays on the buffer (no reference count): the same numbers and
    memory as the slices."""
    a, b, c = np.arange(3.0), np.arange(6.0).reshape(2, 3), np.arange(24.0).reshape(2, 3, 4)
    buf, index = pack([a, b, c])
    src = np.arange(12, dtype=np.int64).reshape(3, 4)
    got = _compiled_views(buf, index, src)
    for x, y in zip(got, (a, b, c, src), strict=True):
        np.testing.assert_array_equal(x, y)
        assert x.dtype == y.dtype
    assert v3(buf, index, 2)[1, 2, 3] == -1.0
    assert _compiled_views(buf, index, src[:, ::2])[3].tolist() == src[:, ::2].tolist()  # not contiguous: as is


def test_estimator_buffers_are_the_stages(settings, design):
    est = E.Estimator(settings, design)
    assert tuple(est.states) == E.STAGE_NAMES == tuple(est.outputs) == tuple(est.params)
    for k, stage in enumerate(E.STAGES):
        assert est.outputs[stage.name].size == stage.outputs.size
        np.testing.assert_array_equal(est.params[stage.name], stage.params_vector(settings, design))
        for j, table in enumerate(stage.table_arrays(design)):
            np.testing.assert_array_equal(v1(est._tables, est._table_index, E.TABLE_ROW0[k] + j), table.ravel())
    # the views write through to the buffer the step reads
    est.states["supervisor"][0] = 12.5
    assert 12.5 in est._state


def test_set_initial_stiffness_scale_starts_from_scaled_tyres_not_restored(settings, design):
    from ptw_rt.core import stiffness as stf

    est = E.Estimator(settings, design)
    nominal, bound = design.ad_theta_nominal, design.ad_theta_bound
    est.set_initial_stiffness_scale(0.8, 1.2)
    # the tyre bank (one scale): the geometric mean; seed 001's observer: per axle, clipped to its bounds
    np.testing.assert_allclose(est.learned_stiffness(), nominal * np.sqrt(0.8 * 1.2))
    expected = np.clip(nominal * np.array([0.8, 0.8, 1.2, 1.2]), nominal - bound, nominal + bound)
    np.testing.assert_allclose(stf.learned(est.states["stiffness"], design), expected)
    assert est.states["stiffness"][stf.ST_RESTORED] == 0.0
    est.set_initial_stiffness_scale(0.1, 0.1)  # clipped to the bank's smallest hypothesis
    np.testing.assert_allclose(est.learned_stiffness(), nominal * design.tb_scale[0])
    est.reset()  # a start value survives a reset like a learned one
    np.testing.assert_allclose(est.learned_stiffness(), nominal * design.tb_scale[0])
    with pytest.raises(ValueError):
        est.set_initial_stiffness_scale(float("nan"), 1.0)
    est.restore_stiffness(nominal)
    assert est.states["stiffness"][stf.ST_RESTORED] == 1.0


def test_stage_index_names_match_the_order():
    """`estimator.INPUTS`, `SPEED`, ...: the index of each stage is named after it (upper case)."""
    assert len(set(E.STAGE_NAMES)) == E.N_STAGES
    for k, name in enumerate(E.STAGE_NAMES):
        assert getattr(E, name.upper()) == k, f"estimator.{name.upper()} is not the index of stage {name}"
