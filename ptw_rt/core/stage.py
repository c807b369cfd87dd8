"""What a stage of the estimator is, how its numbers are laid out, and how the stages are packed for one call.

A **stage** is one jitted function per cycle (`attitude.attitude_stage`, `kalman.lateral_stage`, ...) that
owns three flat float64 arrays, each with a **named layout** declared once, next to the function:

- ``state``: what it carries from cycle to cycle (filter states, clocks, and its own scratch);
- ``params``: numbers from the config and the design file, built by the stage's ``build_params(settings,
  design)`` (the one place where that stage's configuration becomes numbers), constant while running;
- ``outputs``: what it tells the stages after it and the published record, rewritten every cycle.

and optionally **tables** (design arrays scheduled over the speed grid, named as in ``DesignData``). A stage
reads the outputs of the stages before it through their named indices, never another stage's state.

**Layouts.** A ``Layout`` is a small declarative table of ``(name, size)`` fields in order; the module then
unpacks its offsets into plain named constants::

    STATE = Layout("ST_", init=1, last=8, steer_jumps=1)
    ST_INIT, ST_LAST, ST_STEER_JUMPS = STATE.offsets
    STATE_SIZE = STATE.size

Why both: numba freezes module-level integers into the compiled code as constants, so the hot path indexes
with named constants at no cost, and ``grep ST_LAST`` finds every use; the table gives the sizes, the
offsets without hand arithmetic, the names for the documentation, and ``Layout.vector`` (parameters filled
by name: a missing or unknown name is an error). ``tests/test_stage_layouts.py`` checks that every
constant matches its table entry (``PREFIX + NAME``), so the unpacking order cannot drift.

**Packing** (why the estimator is called with two flat buffers): numba unboxes every array argument of a
call from Python (~0.15 us each). The estimator keeps every stage's state and outputs in one flat buffer and
every stage's parameters and tables in another, plus an index array for each: row ``[start, stop, dim0,
dim1, dim2]`` per part. ``v1``/``v2``/``v3`` rebuild views inside compiled code, where they cost nothing (no
allocation: slices and reshapes of contiguous buffers). ``pack`` builds a buffer and its index.

**Reference counting** (why the hot path looks the way it does). numba counts references to every array: a
view made in compiled code shares its buffer's count, and every array variable, argument and view costs a
call of NRT_incref and NRT_decref; on a counted array they are atomic (~6 ns each: a third of the step's time
when every view was a slice). ``v1``/``v2``/``v3`` and ``borrowed`` (below) make arrays without a count, so
the calls do nothing, but they are still calls (~2 ns each with the registers saved around them: ~430 a
cycle, 0.8 us); the stages' step functions are therefore ``inline="always"``, which lets numba drop most of
them. Outputs are bit for bit the same either way.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic, overload


class Layout:
    """Named fields of one flat float64 array, in order: ``Layout("ST_", init=1, last=8)``.

    ``prefix`` is the prefix of the module constants that hold the offsets (``ST_INIT``, ``ST_LAST``).
    """

    def __init__(self, prefix: str, **fields: int) -> None:
        self.prefix = prefix
        self.fields: tuple[tuple[str, int], ...] = tuple((name, int(size)) for name, size in fields.items())
        self.offset: dict[str, int] = {}
        start = 0
        for name, size in self.fields:
            if size < 1:
                raise ValueError(f"layout field {name}: size must be >= 1, got {size}")
            self.offset[name] = start
            start += size
        self.size = start

    @property
    def offsets(self) -> tuple[int, ...]:
        return tuple(self.offset[name] for name, _ in self.fields)

    def constant_names(self) -> tuple[str, ...]:
        """The names the module's constants must have, in field order."""
        return tuple(self.prefix + name.upper() for name, _ in self.fields)

    def slice(self, name: str) -> slice:
        size = dict(self.fields)[name]
        return slice(self.offset[name], self.offset[name] + size)

    def vector(self, values: Mapping[str, object] | None = None, strict: bool = True, **kw) -> np.ndarray:
        """A zero-filled vector of this layout with the named fields set (arrays for fields wider than 1).

        ``strict``: every field must be given (a parameter forgotten is an error, not a silent zero).
        """
        given = dict(values or {}, **kw)
        unknown = set(given) - set(self.offset)
        if unknown:
            raise KeyError(f"not in the layout: {sorted(unknown)}")
        missing = [name for name, _ in self.fields if name not in given]
        if strict and missing:
            raise KeyError(f"not given: {missing}")
        v = np.zeros(self.size)
        for name, value in given.items():
            v[self.slice(name)] = value
        return v

    def describe(self) -> str:
        """``name[size]`` in order, for documentation."""
        return ", ".join(name if size == 1 else f"{name}[{size}]" for name, size in self.fields)


class StageBuffers(NamedTuple):
    """One stage's arrays on their own (``Stage.alone``): its tables packed from row 0."""

    state: np.ndarray
    params: np.ndarray
    outputs: np.ndarray
    tables: np.ndarray
    tindex: np.ndarray


def _zeros(layout: Layout) -> Callable[..., np.ndarray]:
    return lambda settings, design: np.zeros(layout.size)


@dataclass(frozen=True)
class Stage:
    """Everything the estimator needs to know to give a stage its buffers (one per stage module).

    ``tables``: ``(name, ndim)`` of the design tables the stage reads, in the order its jitted function takes
    them (``t0 + k`` is table ``k`` for a stage whose first table row is ``t0``); ``constants`` supplies a
    table that is not in the design file (an array, or a function of the design that makes it).
    ``new_state(settings, design)``: the initial state (default zeros of the layout; a stage whose state size
    depends on the config makes its own, at least ``state.size`` long).
    ``reset(state, params)``: what ``Estimator.reset`` does to its state (default: all zero); the parameters say
    how the state is laid out where that depends on the design (the tyre bank's hypotheses).
    """

    name: str
    state: Layout
    params: Layout
    outputs: Layout
    build_params: Callable[..., np.ndarray]
    tables: tuple[tuple[str, int], ...] = ()
    constants: Mapping[str, np.ndarray | Callable[..., np.ndarray]] = field(default_factory=dict)
    new_state: Callable[..., np.ndarray] | None = None
    reset: Callable[[np.ndarray, np.ndarray], None] | None = None
    doc: str = ""

    def initial_state(self, settings, design) -> np.ndarray:
        make = self.new_state or _zeros(self.state)
        state = np.asarray(make(settings, design), dtype=np.float64)
        if state.ndim != 1 or state.size < self.state.size:
            raise ValueError(f"stage {self.name}: state of {state.shape}, layout needs {self.state.size}")
        return state

    def params_vector(self, settings, design) -> np.ndarray:
        prm = np.asarray(self.build_params(settings, design), dtype=np.float64)
        if prm.shape != (self.params.size,):
            raise ValueError(f"stage {self.name}: parameters of shape {prm.shape}, layout has {self.params.size}")
        return prm

    def table_arrays(self, design) -> list[np.ndarray]:
        out = []
        for name, ndim in self.tables:
            if name in self.constants:  # a fixed array, or one made from the design (a callable)
                constant = self.constants[name]
                table = np.asarray(constant(design) if callable(constant) else constant)
            else:
                table = np.asarray(getattr(design, name))
            if table.ndim != ndim:
                raise ValueError(f"stage {self.name}: table {name} has {table.ndim} dimensions, expected {ndim}")
            out.append(table)
        return out

    def alone(self, settings, design) -> StageBuffers:
        """Fresh buffers to run this stage without the others (a unit test): call its function with
        ``tables, tindex, 0`` and upstream outputs made with their ``OUTPUTS.vector(..., strict=False)``."""
        tables, tindex = pack(self.table_arrays(design))
        return StageBuffers(
            self.initial_state(settings, design),
            self.params_vector(settings, design),
            np.zeros(self.outputs.size),
            tables,
            tindex,
        )

    def reset_state(self, state: np.ndarray, params: np.ndarray) -> None:
        if self.reset is None:
            state[:] = 0.0
        else:
            self.reset(state, params)


def pack(arrays) -> tuple[np.ndarray, np.ndarray]:
    """One flat float64 buffer and its index rows [start, stop, dims...] for C-ordered arrays (<= 3-D)."""
    index = np.zeros((len(arrays), 5), dtype=np.int64)
    start = 0
    for k, a in enumerate(arrays):
        index[k, 0], index[k, 1] = start, start + a.size
        index[k, 2 : 2 + a.ndim] = a.shape
        start += a.size
    buf = np.zeros(max(start, 1))
    for k, a in enumerate(arrays):
        buf[index[k, 0] : index[k, 1]] = np.ascontiguousarray(a, dtype=np.float64).ravel()
    return buf, index


def pack_tables(stage: Stage, design) -> tuple[np.ndarray, np.ndarray]:
    """A stage's tables alone, packed (first table row 0): how a test calls one stage on the design file."""
    return pack(stage.table_arrays(design))


# Views and borrowed arrays without reference counting. A slice in compiled code shares its buffer's reference
# count: every view made, and every array handed to a function that is not inlined, costs an atomic increment
# and decrement of it (about 600 a cycle, a third of the step's time). Compiled, ``v1``/``v2``/``v3`` and
# ``borrowed`` make their arrays with ``carray`` on the buffer's address instead: no reference count, and a 2-D
# or 3-D view needs no call to reshape. Safe because none outlives the call that holds the buffer: the stages
# get views of ``packed_step``'s arguments and keep none. The Python functions are what runs with numba's JIT
# off (the ordinary slices); a buffer that is not C-contiguous gets them too.


@intrinsic
def _float64_at(typingctx, address):
    """The integer ``address`` as a float64 pointer (for ``carray``)."""
    sig = types.CPointer(types.float64)(types.intp)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.float64)))

    return sig, codegen


@intrinsic
def _data_pointer(typingctx, a):
    """A C-contiguous array's data pointer (for ``carray``)."""
    if not isinstance(a, types.Array) or a.layout != "C":
        return None
    sig = types.CPointer(a.dtype)(a)

    def codegen(context, builder, signature, args):
        return context.make_array(signature.args[0])(context, builder, args[0]).data

    return sig, codegen


def _contiguous_float64(buf) -> bool:
    return isinstance(buf, types.Array) and buf.layout == "C" and buf.dtype == types.float64


def borrowed(a: np.ndarray) -> np.ndarray:
    """The same array, without its reference count when compiled (for the arguments of a compiled loop or step
    that hands them on to other compiled functions; valid while the caller holds ``a``: within the call)."""
    return a


@overload(borrowed, inline="always")
def _borrowed_compiled(a):
    if isinstance(a, types.Array) and a.layout == "C":
        return lambda a: carray(_data_pointer(a), a.shape)
    return lambda a: a


def v1(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]]


def v2(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]].reshape((index[k, 2], index[k, 3]))


def v3(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]].reshape((index[k, 2], index[k, 3], index[k, 4]))


@overload(v1, inline="always")
def _v1_compiled(buf, index, k):
    if not _contiguous_float64(buf):
        return v1
    return lambda buf, index, k: carray(_float64_at(buf.ctypes.data + 8 * index[k, 0]), (index[k, 1] - index[k, 0],))


@overload(v2, inline="always")
def _v2_compiled(buf, index, k):
    if not _contiguous_float64(buf):
        return v2
    return lambda buf, index, k: carray(_float64_at(buf.ctypes.data + 8 * index[k, 0]), (index[k, 2], index[k, 3]))


@overload(v3, inline="always")
def _v3_compiled(buf, index, k):
    if not _contiguous_float64(buf):
        return v3
    return lambda buf, index, k: carray(
        _float64_at(buf.ctypes.data + 8 * index[k, 0]), (index[k, 2], index[k, 3], index[k, 4])
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def all_finite(v: np.ndarray, n: int) -> bool:
    """The first n entries are finite (the stages' guard before they trust an observer's state)."""
    for i in range(n):
        if not math.isfinite(v[i]):
            return False
    return True
