"""Hostile inputs for every file ptw-rt reads, built at test time (nothing large is committed).

Each builder writes into a session directory and returns a path; ``/dev/zero`` and a FIFO stand for the
non-regular files. Sparse files stand for the huge ones: the size check must refuse them from ``fstat`` alone.
"""

from __future__ import annotations

import io
import json
import os
import random
import resource
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN

MEMORY_LIMIT = 1536 << 20  # RLIMIT_AS of every CLI subprocess: 1.5 GiB
LOG_EPOCH = 1_700_000_000.0


def _write(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def _sparse(path: Path, size: int) -> Path:
    with open(path, "wb") as fh:
        fh.truncate(size)  # a hole: costs no disk and no time
    return path


def _common(d: Path, prefix: str) -> dict[str, Path]:
    """The non-regular and degenerate files every reader must refuse cleanly."""
    fifo = d / f"{prefix}.fifo"
    if not fifo.exists():
        os.mkfifo(fifo)
    subdir = d / f"{prefix}.dir"
    subdir.mkdir(exist_ok=True)
    rng = random.Random(13)
    return {
        "fifo": fifo,
        "dev_zero": Path("/dev/zero"),
        "directory": subdir,
        "empty": _write(d / f"{prefix}.empty", b""),
        "random_bytes": _write(d / f"{prefix}.random", bytes(rng.randrange(256) for _ in range(20000))),
        "huge_sparse": _sparse(d / f"{prefix}.huge", 100 << 20),
    }


def _alias_bomb(levels: int) -> str:
    lines = ["a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    for i in range(1, levels + 1):
        refs = ", ".join([f"*a{i - 1}"] * 9)
        lines.append(f"a{i}: &a{i} [{refs}]")
    return "\n".join(lines) + "\n"


def build_configs(d: Path) -> dict[str, Path]:
    good = DEFAULT_CONFIG.read_text(encoding="utf-8")
    files = _common(d, "config")
    files.update(
        {
            "alias_bomb": _write(d / "alias_bomb.yaml", _alias_bomb(9)),
            # the bomb as the value of a real key, so a validator that expanded it would quote gigabytes
            "alias_bomb_as_value": _write(
                d / "alias_bomb_value.yaml", _alias_bomb(8) + good.replace("vehicle:", "vehicle_x: *a8\nvehicle:", 1)
            ),
            "nested_brackets": _write(d / "nested.yaml", "a: " + "[" * 50_000 + "]" * 50_000 + "\n"),
            "nested_braces": _write(d / "nested_braces.yaml", "a: " + "{b: " * 50_000 + "1" + "}" * 50_000 + "\n"),
            "non_utf8": _write(d / "latin1.yaml", good.replace("name:", "name: caf\xe9 #", 1).encode("latin-1")),
            "comments_over_limit": _write(d / "comments.yaml", "# " + "x" * 78 + "\n" * 1 + ("#" * 79 + "\n") * 4000),
            "huge_integer": _write(d / "bigint.yaml", "a: " + "9" * 100_000 + "\n"),
            "long_bad_value": _write(
                d / "long_value.yaml",
                good.replace("vehicle:", "vehicle:\n  mass_oops: [" + ", ".join(["1"] * 5000) + "]", 1),
            ),
            "long_bad_text": _write(d / "long_text.yaml", "vehicle: '" + "x" * 200_000 + "'\n"),
            "long_key": _write(d / "long_key.yaml", good.replace("vehicle:", "k" * 100_000 + ": 1\nvehicle:", 1)),
            "binary_tag": _write(d / "tag.yaml", "a: !!python/object:os.system [echo pwned]\n"),
            "bad_date": _write(d / "date.yaml", "a: 2024-13-45\n"),
            # explicit tags PyYAML's constructors cannot read raise KeyError / IndexError / AttributeError (fuzzing,
            # 2026-11-26): tracebacks
            "tag_bool_maybe": _write(d / "tag_bool.yaml", 'a: !!bool "maybe"\n'),
            "tag_int_empty": _write(d / "tag_int.yaml", 'a: !!int ""\n'),
            "tag_int_sign": _write(d / "tag_int_sign.yaml", 'a: !!int "-"\n'),
            "tag_float_empty": _write(d / "tag_float.yaml", 'a: !!float ""\n'),
            "tag_timestamp": _write(d / "tag_timestamp.yaml", 'a: !!timestamp "abc"\n'),
            # a NUL in a file name passed --check-config and was a ValueError traceback when the daemon opened it
            "state_file_nul": _write(
                d / "state_nul.yaml",
                good.replace("state_file: /var/lib/ptw-rt/state.json", 'state_file: "/tmp/a\\0b"', 1),
            ),
            "many_nodes": _write(d / "nodes.yaml", "".join(f"k{i}: [1, 2]\n" for i in range(20_000))[:250_000]),
            # values within the schema's ranges that admit no design or no simulated rider (found by fuzzing,
            # 2026-11-26): numpy's LinAlgError / ArithmeticError / MemoryError reached the user as tracebacks
            "grid_too_fine": _write(d / "grid_fine.yaml", good.replace("step_kmh: 2.5", "step_kmh: 1.0e-9", 1)),
            "no_design": _write(
                d / "no_design.yaml", good.replace("relaxation_length: 0.2 ", "relaxation_length: 1.0e-12 ", 1)
            ),
            "duplicate_key": _write(
                d / "duplicate.yaml", good.replace("estimator:\n", "estimator:\n  sample_time: 0.02\n", 1)
            ),
        }
    )
    return files


def _npy(name: str, header: dict, payload: bytes) -> tuple[str, bytes]:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return f"{name}.npy", buf.getvalue() + payload


def build_designs(d: Path) -> dict[str, Path]:
    files = _common(d, "design")
    good = dict(np.load(DEFAULT_DESIGN, allow_pickle=False))

    # 1. the classic bomb: 100 MB of zeros in one member, ~100 kB compressed
    bomb = d / "zip_bomb.npz"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("uh_Phi.npy", "w", force_zip64=True) as member:
            name, head = _npy("uh_Phi", {"descr": "<f8", "fortran_order": False, "shape": (100 << 17,)}, b"")
            member.write(head)
            zeros = bytes(1 << 20)
            for _ in range(100):
                member.write(zeros)
    files["zip_bomb"] = bomb

    # 2. a header declaring 49 x 100000 x 100000 doubles (3.6 TB) over a few bytes of data
    lie = d / "shape_lie.npz"
    with zipfile.ZipFile(lie, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in good.items():
            if k != "kf_Phi":
                zf.writestr(f"{k}.npy", _array_bytes(v))
        zf.writestr(*_npy("kf_Phi", {"descr": "<f8", "fortran_order": False, "shape": (49, 100000, 100000)}, bytes(64)))
        zf.writestr("kf_Phi_old.npy", b"")  # an unknown but well-formed name is skipped, never read
    files["shape_lie"] = lie

    # 3. the zip directory claims 144 bytes, the stream inflates to 8 MB: read stops at 144, CRC fails
    crc = d / "size_lie.npz"
    with zipfile.ZipFile(crc, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(
            "grid.npy", _npy("grid", {"descr": "<f8", "fortran_order": False, "shape": (2,)}, bytes(8 << 20))[1]
        )
    raw = bytearray(crc.read_bytes())
    central = raw.rfind(b"PK\x01\x02")
    raw[central + 24 : central + 28] = (144).to_bytes(4, "little")
    raw[22:26] = (144).to_bytes(4, "little")
    crc.write_bytes(bytes(raw))
    files["size_lie"] = crc

    # 4. an object array (np.save would pickle it): must be refused, never unpickled
    pickled = d / "pickle.npz"
    np.savez(pickled, **{**good, "vehicle_name": np.array([{"x": 1}], dtype=object)})
    files["pickle"] = pickled

    # 5. many members
    many = d / "many_members.npz"
    with zipfile.ZipFile(many, "w", zipfile.ZIP_STORED) as zf:
        for i in range(5000):
            zf.writestr(f"m{i}.npy", b"")
    files["many_members"] = many

    # 6. a speed-grid table one grid point short (the jitted step would read past its end)
    short = d / "short_table.npz"
    np.savez(short, **{**good, "kf_K": good["kf_K"][:-1]})
    files["short_grid_table"] = short

    # 7. path traversal / odd member names
    odd = d / "odd_names.npz"
    with zipfile.ZipFile(odd, "w") as zf:
        zf.writestr("../../etc/passwd.npy", b"")
    files["odd_member_name"] = odd

    # 8. a well-formed table with a NaN in it: it would load and run DEGRADED every cycle, with nothing said
    nan = d / "nan_table.npz"
    phi = good["tb_Phi"].copy()
    phi.flat[0] = np.nan
    np.savez(nan, **{**good, "tb_Phi": phi})
    files["nan_table"] = nan
    return files


def _array_bytes(value: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
    return buf.getvalue()


def state_doc(config_hash: str, stiffness: dict) -> str:
    return json.dumps(
        {"format": "ptw-rt-state", "version": 1, "config_hash": config_hash, "saved_at": "x", "stiffness": stiffness}
    )


def build_states(d: Path, config_hash: str, nominal: np.ndarray) -> dict[str, Path]:
    files = _common(d, "state")
    keys = ("front_cornering", "front_camber", "rear_cornering", "rear_camber")

    def values(scale: float | None = None, fixed: float | None = None) -> dict:
        return {k: (fixed if fixed is not None else float(n) * scale) for k, n in zip(keys, nominal, strict=True)}

    files.update(
        {
            "nested_100k": _write(d / "nested100k.json", "[" * 100_000),
            "nested_60k": _write(d / "nested60k.json", "[" * 60_000),  # under the size limit: the depth check
            "nested_objects": _write(d / "nested_obj.json", '{"a":' * 10_000),
            "non_utf8": _write(d / "latin1.json", b'{"format": "ptw-rt-state\xe9"}'),
            "huge_number": _write(
                d / "bignum.json",
                state_doc(config_hash, {**values(1.0), "rear_camber": 0}).replace(
                    '"rear_camber": 0', '"rear_camber": ' + "9" * 20000
                ),
            ),
            "value_1e308": _write(d / "1e308.json", state_doc(config_hash, values(fixed=1e308))),
            "value_x1000": _write(d / "x1000.json", state_doc(config_hash, values(scale=1000.0))),
            "value_1e-300": _write(d / "tiny.json", state_doc(config_hash, values(fixed=1e-300))),
            "value_nan": _write(d / "nan.json", state_doc(config_hash, values(fixed=float("nan")))),
            # the last one would win: an absurd first value hidden behind a plausible second
            "duplicate_key": _write(
                d / "dup.json",
                state_doc(config_hash, values(1.0)).replace(
                    '"front_cornering": ', '"front_cornering": 1e9, "front_cornering": ', 1
                ),
            ),
        }
    )
    return files


def log_line(t: float, frame_id: int = 0x100, data: str = "0000000000000000") -> str:
    return f"({t:017.6f}) vcan0 {frame_id:03X}#{data}"


def clean_log_lines(seconds: float = 2.0) -> list[str]:
    """A plausible little log: the three 100 Hz sensor ids every 10 ms."""
    lines = []
    for k in range(int(seconds * 100)):
        t = LOG_EPOCH + k * 0.01
        lines += [log_line(t, 0x100), log_line(t + 0.0003, 0x101), log_line(t + 0.0006, 0x102, "0002")]
    return lines


def shifted(lines: list[str], dt: float) -> list[str]:
    """Log lines with their time stamps moved by ``dt`` seconds."""
    out = []
    for line in lines:
        stamp, rest = line[1:].split(")", 1)
        out.append(f"({float(stamp) + dt:017.6f}){rest}")
    return out


def swapped_pairs(lines: list[str]) -> list[str]:
    """Lines swapped three apart, every sixth line: frames up to 10 ms out of order, as a log of several nodes has."""
    out = list(lines)
    for k in range(0, len(out) - 3, 6):
        out[k], out[k + 3] = out[k + 3], out[k]
    return out


def build_logs(d: Path) -> dict[str, Path]:
    files = _common(d, "log")
    clean = clean_log_lines()
    half = len(clean) // 2

    def log(name: str, lines: list[str]) -> Path:
        return _write(d / f"{name}.log", "\n".join(lines) + "\n")

    files.update(
        {
            "digits_400": log("digits400", ["(" + "9" * 400 + ".000000) vcan0 100#00"] + clean),
            "digits_200_everywhere": log("digits200", ["(" + "1" * 200 + ".5) vcan0 100#00"] * 50 + clean),
            "inf_first": log("inf", ["(inf) vcan0 100#00"] + clean),
            "nan_and_inf": log("naninf", clean[:half] + ["(nan) vcan0 100#00", "(-inf) vcan0 100#00"] + clean[half:]),
            "stray_zero_first": log("stray0", [log_line(0.000001)] + clean),
            "far_future_line": log("future", clean[:half] + ["(99999999999.000000) vcan0 100#00"] + clean[half:]),
            "year_2286_line": log("y2286", clean[:half] + [log_line(9_999_999_999.0)] + clean[half:]),
            "negative": log("negative", ["(-1700000000.000000) vcan0 100#00"] + clean),
            "reversed": log("reversed", list(reversed(clean))),
            "block_5s_in_past": log(
                "past", clean[:half] + [log_line(LOG_EPOCH - 5 + k * 0.01) for k in range(5)] + clean[half:]
            ),
            "long_line": log("longline", clean[:10] + ["(" + "1" * 3_000_000] + clean[10:]),
            # time as hostile data beyond single lines: replay ends a segment at a long gap or a jump back
            "gap_2h": log("gap2h", clean + shifted(clean, 7200.0 + 2.0)),
            "gap_3s": log("gap3s", clean + shifted(clean, 3.0 + 2.0)),  # bridged: within the default --max-gap
            "backwards_30s": log("back30", clean + shifted(clean, -30.0)),
            "swapped_pairs": log("swapped", swapped_pairs(clean)),
            "no_newline_at_all": _write(d / "onelong.log", b"x" * 3_000_000),
        }
    )
    return files


@pytest.fixture(scope="session")
def warm_numba_cache(tmp_path_factory) -> None:
    """The estimator's machine code in the numba cache the CLI subprocesses load (they inherit this process's
    NUMBA_CACHE_DIR). On a cold cache (a fresh install, or the first run after the source changed) each would
    compile it itself, three at a time on two cores, against the tests' timeouts: compiled once here instead,
    in process, by a replay of a clean little log (the work the first replay test would do anyway)."""
    from ptw_rt.apps.replay import replay_log

    d = tmp_path_factory.mktemp("warm")
    log = _write(d / "clean.log", "\n".join(clean_log_lines()) + "\n")
    replay_log(log, d / "out.log", None)


@pytest.fixture(scope="session")
def hostile_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("hostile")


@pytest.fixture(scope="session")
def hostile_configs(hostile_dir) -> dict[str, Path]:
    d = hostile_dir / "config"
    d.mkdir()
    return build_configs(d)


@pytest.fixture(scope="session")
def hostile_designs(hostile_dir) -> dict[str, Path]:
    d = hostile_dir / "design"
    d.mkdir()
    return build_designs(d)


@pytest.fixture(scope="session")
def committed_design():
    from ptw_rt.design.file import load_design

    return load_design(DEFAULT_DESIGN)


@pytest.fixture(scope="session")
def hostile_states(hostile_dir, committed_design) -> dict[str, Path]:
    d = hostile_dir / "state"
    d.mkdir()
    return build_states(d, committed_design.config_hash, committed_design.ad_theta_nominal)


@pytest.fixture(scope="session")
def hostile_logs(hostile_dir) -> dict[str, Path]:
    d = hostile_dir / "logs"
    d.mkdir()
    return build_logs(d)


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def run_cli(args: list[str], cwd: Path, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """``python -m ptw_rt ARGS`` under a 1.5 GiB address-space limit and a timeout."""
    return subprocess.run(
        [sys.executable, "-m", "ptw_rt", *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        errors="replace",
        timeout=timeout,
        preexec_fn=_limit_memory,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )


def run_many(commands: list[list[str]], cwd: Path, timeout: float = 60.0, parallel: int = 3) -> list[tuple]:
    """Several CLI runs at once (each under the memory limit); [(args, returncode, stdout, stderr, seconds)]."""
    pending = list(commands)
    running: list[tuple[list[str], subprocess.Popen, float]] = []
    done = []
    while pending or running:
        while pending and len(running) < parallel:
            args = pending.pop(0)
            proc = subprocess.Popen(
                [sys.executable, "-m", "ptw_rt", *map(str, args)],
                cwd=cwd,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                errors="replace",
                preexec_fn=_limit_memory,
                env={**os.environ, "NUMBA_NUM_THREADS": "1"},
            )
            running.append((args, proc, time.monotonic()))
        args, proc, t0 = running.pop(0)
        try:
            out, err = proc.communicate(timeout=max(1.0, timeout - (time.monotonic() - t0)))
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            done.append((args, None, out, err, time.monotonic() - t0))
            continue
        done.append((args, proc.returncode, out, err, time.monotonic() - t0))
    return done
