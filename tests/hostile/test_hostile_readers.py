"""Every reader of an untrusted file, in-process, against every hostile fixture: a one-line error (or, for the
state file and log content, a one-line reason and counts), in bounded time and memory, never a traceback."""

from __future__ import annotations

import logging
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from ptw_rt.design.file import DesignFileError, load_design
from ptw_rt.errors import UserFacingError
from ptw_rt.io.candump import MAX_LINE_CHARS, read_log
from ptw_rt.io.state_file import load_state, restore_state, save_state, stiffness_bounds
from ptw_rt.paths import DEFAULT_DESIGN
from ptw_rt.schema import ConfigError
from ptw_rt.settings import load_settings
from ptw_rt.untrusted import check_nesting, excerpt, short_text

from .conftest import clean_log_lines, state_doc

MAX_MESSAGE = 400  # characters of one error line (path included)
MAX_SECONDS = 5.0  # generous: a shared 2-core CI machine; the real figures are a few ms to ~0.5 s
MAX_PEAK_MB = 64  # Python-level allocations (tracemalloc; numpy reports its buffers to it)


# The fixtures whose threat is memory (expansion, decompression, endless or huge input): their peak allocation is
# measured with tracemalloc. The others are measured for time only (tracemalloc slows PyYAML ~5x).
MEMORY_THREATS = {
    "dev_zero",
    "huge_sparse",
    "random_bytes",
    "alias_bomb",
    "alias_bomb_as_value",
    "nested_brackets",
    "nested_braces",
    "comments_over_limit",
    "zip_bomb",
    "shape_lie",
    "size_lie",
    "pickle",
    "nested_100k",
    "nested_60k",
    "nested_objects",
    "long_line",
    "no_newline_at_all",
    "digits_400",
}


class Measured:
    def __init__(self, memory: bool = True) -> None:
        self.memory = memory
        self.seconds = 0.0
        self.peak_mb = 0.0

    def __enter__(self) -> Measured:
        if self.memory:
            tracemalloc.start()
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self._t0
        if self.memory:
            self.peak_mb = tracemalloc.get_traced_memory()[1] / 2**20
            tracemalloc.stop()

    def check(self) -> None:
        assert self.seconds < MAX_SECONDS, f"took {self.seconds:.2f} s"
        assert self.peak_mb < MAX_PEAK_MB, f"peak {self.peak_mb:.1f} MB"


def _one_line(message: str) -> None:
    assert message and "\n" not in message and "\r" not in message, repr(message[:200])
    assert len(message) <= MAX_MESSAGE, f"{len(message)} characters: {message[:200]}..."
    assert "Traceback" not in message


def _refused(call, error: type[Exception], memory: bool = True) -> str:
    with Measured(memory) as m, pytest.raises(error) as info:
        call()
    m.check()
    message = str(info.value)
    _one_line(message)
    return message


# ---------------------------------------------------------------------- configuration


CONFIG_NAMES = [
    "fifo",
    "dev_zero",
    "directory",
    "empty",
    "random_bytes",
    "huge_sparse",
    "alias_bomb",
    "alias_bomb_as_value",
    "nested_brackets",
    "nested_braces",
    "non_utf8",
    "comments_over_limit",
    "huge_integer",
    "long_bad_value",
    "long_bad_text",
    "long_key",
    "binary_tag",
    "bad_date",
    "tag_bool_maybe",
    "tag_int_empty",
    "tag_int_sign",
    "tag_float_empty",
    "tag_timestamp",
    "state_file_nul",
    "many_nodes",
]


@pytest.mark.parametrize("name", CONFIG_NAMES)
def test_config_refused_in_one_line(name, hostile_configs):
    path = hostile_configs[name]
    message = _refused(lambda: load_settings(path), ConfigError, memory=name in MEMORY_THREATS)
    assert message.startswith(str(path))


def test_config_messages_say_why(hostile_configs):
    def why(name):
        with pytest.raises(ConfigError) as info:
            load_settings(hostile_configs[name])
        return str(info.value)

    assert "FIFO" in why("fifo")
    assert "character device" in why("dev_zero")
    assert "directory" in why("directory")
    assert "too large" in why("huge_sparse") and "too large" in why("comments_over_limit")
    assert "aliases" in why("alias_bomb") or "anchors" in why("alias_bomb")
    assert "anchors" in why("alias_bomb_as_value")
    assert "nested deeper" in why("nested_brackets") and "nested deeper" in why("nested_braces")
    assert "not UTF-8" in why("non_utf8") and "line " in why("non_utf8")
    assert "digits" in why("huge_integer")
    assert "more than" in why("many_nodes")
    assert "..." in why("long_bad_text")  # the value is quoted as a short excerpt
    assert "explicit tag" in why("tag_bool_maybe") and "explicit tag" in why("tag_timestamp")
    assert "runtime.state_file: a file name with a NUL character" in why("state_file_nul")


def test_good_config_still_loads(settings):
    assert settings.config_hash


# ---------------------------------------------------------------------- design file

DESIGN_NAMES = [
    "fifo",
    "dev_zero",
    "directory",
    "empty",
    "random_bytes",
    "huge_sparse",
    "zip_bomb",
    "shape_lie",
    "size_lie",
    "pickle",
    "many_members",
    "short_grid_table",
    "odd_member_name",
]


@pytest.mark.parametrize("name", DESIGN_NAMES)
def test_design_refused_in_one_line(name, hostile_designs, settings):
    path = hostile_designs[name]
    _refused(lambda: load_design(path, settings.config_hash), DesignFileError, memory=name in MEMORY_THREATS)


def test_design_messages_say_why(hostile_designs):
    def why(name):
        with pytest.raises(DesignFileError) as info:
            load_design(hostile_designs[name])
        return str(info.value)

    assert "decompress to more than" in why("zip_bomb")
    assert "does not match its size" in why("shape_lie")
    assert "CRC" in why("size_lie")
    assert "dtype" in why("pickle") and "object" in why("pickle")
    assert "members" in why("many_members")
    assert "expected (" in why("short_grid_table")
    assert "unexpected member" in why("odd_member_name")


# a design file tampered with, its config hash kept (so the hash check passes): each ran before, some without end
# (a negative sample time: replay wrote 120 MB/s of cycles running backwards), some read past a table's end
TAMPERED = {
    "sample_time_negative": ("sample_time", lambda v: np.array(-0.01), "sample_time"),
    "sample_time_zero": ("sample_time", lambda v: np.array(0.0), "sample_time"),
    "sample_time_tiny": ("sample_time", lambda v: np.array(1e-7), "sample_time"),
    "sample_time_not_the_configs": ("sample_time", lambda v: np.array(0.02), "config's estimator.sample_time"),
    "grid_descending": ("grid", lambda v: v[::-1].copy(), "increasing"),
    "grid_not_the_configs": ("grid", lambda v: v * 1.01, "config's estimator.speed_grid"),
    "table_cut": ("uh_Phi", lambda v: v[:, :2, :2].copy(), "uh_Phi has shape"),
    "one_tyre": ("tb_scale", lambda v: v[:1].copy(), "tb_scale"),
    "observed_code": ("us_observed", lambda v: np.full_like(v, 10**9), "measurement codes"),
    "degree": ("us_degrees", lambda v: np.full_like(v, 9), "us_degrees"),
    "rows": ("uh_complement_rows", lambda v: np.full_like(v, -1), "uh_complement_rows"),
    "mass": ("us_mass", lambda v: np.array(0.0), "us_mass"),
}


@pytest.mark.parametrize("name", sorted(TAMPERED))
def test_a_design_file_tampered_with_its_hash_kept_is_refused(name, tmp_path, settings):
    from ptw_rt.design.file import load_design_for

    field, change, why = TAMPERED[name]
    with np.load(DEFAULT_DESIGN) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays[field] = change(arrays[field])
    path = tmp_path / f"{name}.npz"
    np.savez(path, **arrays)
    with pytest.raises(DesignFileError, match=why) as info:
        load_design_for(settings, path)
    assert "\n" not in str(info.value)


def test_the_design_files_limits_are_the_runtimes():
    from ptw_rt.core import tyre_bank, uio_sensors
    from ptw_rt.design import file

    assert file.MAX_HYPOTHESES == tyre_bank.MAX_COUNT
    assert (file.MAX_RECONSTRUCTED, file.MAX_OBSERVED) == (uio_sensors.MAX_OUT, uio_sensors.MAX_OBS)
    assert file.MAX_DEGREE == uio_sensors.MAX_DIFF - 2
    assert file.MEASUREMENT_CODES == uio_sensors.M_LAT_ACCEL + 1  # M_STEER .. M_LAT_ACCEL = range(4)


def test_committed_design_loads_identically_to_numpy(committed_design):
    np = pytest.importorskip("numpy")

    with np.load(DEFAULT_DESIGN, allow_pickle=False) as npz:
        for name in npz.files:
            assert np.array_equal(np.asarray(getattr(committed_design, name)), npz[name]), name


# ---------------------------------------------------------------------- state file

STATE_NAMES = [
    "fifo",
    "dev_zero",
    "directory",
    "empty",
    "random_bytes",
    "huge_sparse",
    "nested_100k",
    "nested_60k",
    "nested_objects",
    "non_utf8",
    "huge_number",
    "value_1e308",
    "value_x1000",
    "value_1e-300",
    "value_nan",
    "duplicate_key",
]


@pytest.fixture(scope="module")
def bounds(committed_design):
    return stiffness_bounds(committed_design.ad_theta_nominal, committed_design.ad_theta_bound)


@pytest.mark.parametrize("name", STATE_NAMES)
def test_state_refused_with_one_warning_line(name, hostile_states, committed_design, bounds):
    with Measured(name in MEMORY_THREATS) as m:
        loaded = restore_state(hostile_states[name], committed_design.config_hash, bounds)
    m.check()
    assert loaded.state is None
    assert loaded.level == logging.WARNING  # a file was there and was refused: say so loudly
    _one_line(loaded.reason)


@pytest.mark.parametrize("name", ["value_1e308", "value_x1000", "value_1e-300"])
def test_absurd_learned_values_are_rejected_not_clipped(name, hostile_states, committed_design, bounds):
    state, reason = load_state(hostile_states[name], committed_design.config_hash, bounds)
    assert state is None
    assert "refused whole" in reason and "outside the learnable range" in reason


def test_a_key_written_twice_refuses_the_state_file(hostile_states, committed_design, bounds):
    state, reason = load_state(hostile_states["duplicate_key"], committed_design.config_hash, bounds)
    assert state is None and "front_cornering" in reason and "written twice" in reason


def test_state_within_bounds_restores(tmp_path, committed_design, bounds):
    design = committed_design
    path = tmp_path / "state.json"
    for values in (
        design.ad_theta_nominal,
        design.ad_theta_nominal + design.ad_theta_bound,  # a learned value at the projection bound
        design.ad_theta_nominal - design.ad_theta_bound,
    ):
        save_state(path, values, design.config_hash)
        loaded = restore_state(path, design.config_hash, bounds)
        assert loaded.state is not None, loaded.reason
        assert loaded.level == logging.INFO


def test_missing_state_file_is_quiet(tmp_path, committed_design, bounds):
    loaded = restore_state(tmp_path / "none.json", committed_design.config_hash, bounds)
    assert loaded.state is None and loaded.level == logging.INFO and "no state file" in loaded.reason


def test_orphan_temp_files_removed_at_start(tmp_path, committed_design, bounds):
    path = tmp_path / "state.json"
    save_state(path, committed_design.ad_theta_nominal, committed_design.config_hash)
    orphans = [tmp_path / f".state.json.k{i}x.tmp" for i in range(9)]  # what SIGKILL during saves leaves
    for p in orphans:
        p.write_text("{")
    other = tmp_path / ".other.json.abc.tmp"  # not ours: kept
    other.write_text("x")
    target = tmp_path / "elsewhere"
    target.write_text("keep")
    (tmp_path / ".state.json.link.tmp").symlink_to(target)  # a symlink is never followed nor removed
    loaded = restore_state(path, committed_design.config_hash, bounds)
    assert loaded.state is not None
    assert sorted(Path(p).name for p in loaded.removed_temp_files) == sorted(p.name for p in orphans)
    assert not any(p.exists() for p in orphans)
    assert other.exists() and target.read_text() == "keep" and (tmp_path / ".state.json.link.tmp").is_symlink()


def test_state_another_config_hash_in_the_document_is_quoted_short(tmp_path, bounds):
    path = tmp_path / "state.json"
    path.write_text(state_doc("\n" * 5000 + "x" * 5000, {}))
    state, reason = load_state(path, "abc", bounds)
    assert state is None
    _one_line(reason)


# ---------------------------------------------------------------------- candump logs

LOG_FILES_REFUSED = ["fifo", "dev_zero", "directory", "huge_sparse"]


@pytest.mark.parametrize("name", LOG_FILES_REFUSED)
def test_log_file_refused_in_one_line(name, hostile_logs):
    path = hostile_logs[name]

    def call():
        reader = read_log(path, max_bytes=50 << 20)  # the size check, scaled to a sparse test file
        list(reader)

    _refused(call, UserFacingError, memory=name in MEMORY_THREATS)


CLEAN_FRAMES = len(clean_log_lines())
LOG_CONTENT = {
    # name: (reason counted, frames expected: None = any)
    "empty": (None, 0),
    "random_bytes": ("malformed", 0),
    "digits_400": ("too_long", CLEAN_FRAMES),
    "digits_200_everywhere": ("bad_timestamp", CLEAN_FRAMES),
    "inf_first": ("bad_timestamp", CLEAN_FRAMES),
    "nan_and_inf": ("bad_timestamp", CLEAN_FRAMES),
    "stray_zero_first": ("time_jump", CLEAN_FRAMES),
    "far_future_line": ("bad_timestamp", CLEAN_FRAMES),
    "year_2286_line": ("bad_timestamp", CLEAN_FRAMES),
    "negative": ("bad_timestamp", CLEAN_FRAMES),
    "reversed": ("time_jump", None),  # at the start: no 8 frames agree on a time base but the last few
    "block_5s_in_past": ("out_of_order", CLEAN_FRAMES),
    "long_line": ("too_long", CLEAN_FRAMES),
    "no_newline_at_all": ("too_long", 0),
}


@pytest.mark.parametrize("name", sorted(LOG_CONTENT))
def test_log_content_rejected_per_line_and_counted(name, hostile_logs, caplog):
    reason, n_frames = LOG_CONTENT[name]
    with caplog.at_level(logging.WARNING, logger="ptw_rt.io.candump"), Measured(name in MEMORY_THREATS) as m:
        reader = read_log(hostile_logs[name])
        frames = list(reader)
    m.check()
    if n_frames is not None:
        assert len(frames) == n_frames
    if reason is not None:
        assert reader.rejected[reason] >= 1, reader.rejected
    assert reader.malformed == sum(reader.rejected.values())
    stamps = [f.timestamp for f in frames]
    assert all(0 <= t < 7258118400.0 for t in stamps)
    # what passes on moves forward, except within the reorder tolerance or at a counted discontinuity
    backwards = sum(1 for a, b in zip(stamps, stamps[1:], strict=False) if b < a - reader.reorder_tolerance)
    assert backwards <= reader.discontinuities
    for record in caplog.records:  # warnings quote at most 80 characters of a line
        message = record.getMessage()
        assert "\n" not in message and len(message) < len(str(hostile_logs[name])) + MAX_LINE_CHARS + 200


@pytest.mark.parametrize("name", sorted(LOG_CONTENT))
def test_a_gzip_compressed_hostile_log_reads_as_its_plain_self(name, hostile_logs, tmp_path):
    """The same hostile lines inside gzip (``ptw_rt.io.compressed``): the same frames and the same counts; or, for a
    log that packs beyond the bound (a 3 MB line of one digit: 200 times), the one-line refusal of a gzip bomb."""
    import gzip

    from ptw_rt.io.compressed import EXPANSION_SLACK, MAX_EXPANSION

    packed = tmp_path / f"{name}.log.gz"
    data = hostile_logs[name].read_bytes()
    packed.write_bytes(gzip.compress(data, 1))
    if len(data) > MAX_EXPANSION * packed.stat().st_size + EXPANSION_SLACK:
        _refused(lambda: list(read_log(packed)), UserFacingError, memory=True)
        return
    plain, compressed = read_log(hostile_logs[name], max_warnings=0), read_log(packed, max_warnings=0)
    with Measured(name in MEMORY_THREATS) as m:
        assert list(compressed) == list(plain)
    m.check()
    assert compressed.rejected == plain.rejected and compressed.discontinuities == plain.discontinuities


def test_log_problems_are_bounded(tmp_path):
    path = tmp_path / "junk.log"
    path.write_bytes(b"junk\n" * 200_000)
    reader = read_log(path, max_warnings=0)
    assert list(reader) == []
    assert reader.malformed == 200_000 and len(reader.problems) <= 1000 and len(reader.malformed_lines) <= 1000


def test_fifo_open_does_not_block(hostile_logs, hostile_configs):
    # the FIFO has no writer: a plain open() would block forever (the test would hit the pytest timeout)
    t0 = time.monotonic()
    for path in (hostile_logs["fifo"], hostile_configs["fifo"]):
        with pytest.raises(UserFacingError, match="FIFO"):
            read_log(path)
    assert time.monotonic() - t0 < 1.0


# ---------------------------------------------------------------------- the helpers themselves


def test_excerpt_is_short_and_escaped():
    deep: list = []
    cursor = deep
    for _ in range(10_000):
        cursor.append([])
        cursor = cursor[0]
    for value in ("x" * 10**6, "a\nb\x00\u202e" * 100, deep, list(range(10**5)), {str(i): i for i in range(10**4)}):
        text = excerpt(value)
        assert len(text) <= 60 and "\n" not in text and text.isascii()


def test_short_text_escapes_control_characters():
    """An ESC sequence in a parser's message (asammdf's, a log line's) was passed to the terminal reading it."""
    text = short_text("a\nb\x1b[2J\x07\x00\x7f\u00e9 c")
    assert text == "a b\\x1b[2J\\x07\\x00\\x7f\\xe9 c" and text.isprintable()


def test_check_nesting_ignores_brackets_in_strings():
    assert check_nesting('{"a": "[[[[[[[[[[[[", "b": [1, {"c": "\\"[["}]}', 3, "x") == 3
    with pytest.raises(ValueError, match="deeper than 3"):
        check_nesting("[[[[1]]]]", 3, "x")


def test_non_regular_file_kinds_named(tmp_path):
    from ptw_rt.untrusted import read_bounded

    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    for path, word in ((fifo, "FIFO"), (Path("/dev/null"), "character device"), (tmp_path, "directory")):
        with pytest.raises(ValueError, match=word):
            read_bounded(path, max_bytes=10)
