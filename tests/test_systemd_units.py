"""The systemd units: `systemd-analyze verify` clean, and the settings the daemon relies on actually present."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path, PurePosixPath

import pytest

SYSTEMD_DIR = Path(__file__).resolve().parents[1] / "systemd"
UNITS = ("ptw-rt.service", "ptw-rt-can0.service", "ptw-rt-vcan0.service")
EXEC_KEYS = ("ExecStart", "ExecStartPre", "ExecStartPost", "ExecReload", "ExecStop", "ExecStopPost")


def parse_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A tiny systemd.syntax(7) parser: sections -> key -> every value in order (keys may repeat).

    Comments (``#``/``;`` at line start), backslash continuation lines; an empty assignment resets the list,
    as systemd does for list settings."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    pending = ""
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not pending and (not line or line[0] in "#;"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line, pending = pending + line, ""
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None, f"{path.name}: assignment outside a section: {raw!r}"
        key, sep, value = line.partition("=")
        assert sep, f"{path.name}: not KEY=VALUE: {raw!r}"
        values = current.setdefault(key.strip(), [])
        if value.strip():
            values.append(value.strip())
        else:
            values.clear()
    return sections


def _one(section: dict[str, list[str]], key: str) -> str:
    values = section.get(key, [])
    assert values, f"{key}= is missing"
    return values[-1]


def _environment(section: dict[str, list[str]]) -> dict[str, str]:
    env = {}
    for value in section.get("Environment", []):
        for item in shlex.split(value):
            name, _, val = item.partition("=")
            env[name] = val
    return env


def _seconds(value: str) -> float:
    """systemd.time(7) spans as used here: '2s', '500ms', '1min 30s', '120'."""
    units = {"us": 1e-6, "ms": 1e-3, "s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
    total = 0.0
    for number, unit in re.findall(r"(\d+(?:\.\d+)?)\s*([a-z]*)", value):
        total += float(number) * units[unit or "s"]
    return total


@pytest.fixture(scope="module")
def units():
    return {name: parse_unit(SYSTEMD_DIR / name) for name in UNITS}


@pytest.fixture(scope="module")
def service(units):
    return units["ptw-rt.service"]["Service"]


def test_all_units_exist():
    for name in (*UNITS, "ptw-rt.sysusers.conf", "README.md"):
        assert (SYSTEMD_DIR / name).is_file(), f"systemd/{name} is missing"


def test_notify_watchdog_restart(service):
    assert _one(service, "Type") == "notify"
    assert _one(service, "NotifyAccess") == "main"
    watchdog = _seconds(_one(service, "WatchdogSec"))
    assert 0.5 <= watchdog <= 30
    assert _one(service, "Restart") == "on-failure"
    assert _seconds(_one(service, "TimeoutStartSec")) >= 30  # numba cold-cache compile before READY=1
    # exit code 2 = UserFacingError (bad config): restarting cannot help
    assert "2" in _one(service, "RestartPreventExitStatus").split()


def test_exec_start_runs_the_daemon_with_a_config(service):
    argv = shlex.split(_one(service, "ExecStart"))
    assert PurePosixPath(argv[0]).is_absolute() and PurePosixPath(argv[0]).name == "ptw-rt"
    assert argv[1:3] == ["run", "--config"], argv
    assert len(argv) == 4 and argv[3].startswith("/etc/ptw-rt/")
    assert _one(service, "ConfigurationDirectory") == "ptw-rt"
    assert "kill -HUP $MAINPID" in _one(service, "ExecReload")


def test_dedicated_user(service):
    dynamic = service.get("DynamicUser", ["no"])[-1] in ("yes", "true", "1")
    user = service.get("User", [""])[-1]
    assert dynamic or (user and user != "root"), "needs User= (a dedicated user) or DynamicUser=yes"
    if user:
        sysusers = (SYSTEMD_DIR / "ptw-rt.sysusers.conf").read_text().splitlines()
        declared = [ln.split()[1] for ln in sysusers if ln.split()[:1] == ["u"]]
        assert user in declared, f"User={user} is not created by ptw-rt.sysusers.conf"


def test_hardening(service):
    assert _one(service, "ProtectSystem") == "strict"
    assert _one(service, "NoNewPrivileges") == "yes"
    assert _one(service, "ProtectHome") == "yes"
    families = " ".join(service.get("RestrictAddressFamilies", [])).split()
    assert {"AF_CAN", "AF_UNIX", "AF_NETLINK"} <= set(families), families
    assert not any(f.startswith("~") for f in families), "must be an allow list"
    # settings that would break the daemon (see comments in the unit)
    assert service.get("MemoryDenyWriteExecute", ["no"])[-1] != "yes", "numba JIT needs W+X memory"
    assert service.get("RestrictRealtime", ["no"])[-1] != "yes", "would forbid SCHED_FIFO"
    assert service.get("PrivateNetwork", ["no"])[-1] != "yes", "would hide can0"
    assert service.get("PrivateDevices", ["no"])[-1] != "yes", "would hide the serial GNSS receiver"


def test_realtime_limits(service):
    assert _one(service, "CPUSchedulingPolicy") == "fifo"
    priority = int(_one(service, "CPUSchedulingPriority"))
    assert 1 <= priority <= 49  # below PREEMPT_RT's IRQ threads (50)
    assert int(_one(service, "LimitRTPRIO")) >= priority
    assert _one(service, "LimitMEMLOCK") == "infinity"  # realtime.py locks memory only then
    env = _environment(service)
    assert env.get("NUMBA_NUM_THREADS") == "1"


def test_state_and_cache_directories(service):
    from ptw_rt.settings import runtime_defaults

    state_dir = _one(service, "StateDirectory").split()[0]
    state_file = PurePosixPath(runtime_defaults().state_file)
    assert state_file.parent == PurePosixPath("/var/lib") / state_dir, (
        f"runtime.state_file default {state_file} is not inside StateDirectory={state_dir} (/var/lib/{state_dir}): "
        "ProtectSystem=strict would make it read-only"
    )
    cache_dir = _one(service, "CacheDirectory").split()[0]
    numba = _environment(service).get("NUMBA_CACHE_DIR", "")
    resolved = numba.replace("%C", "/var/cache")
    assert PurePosixPath(resolved).is_relative_to(PurePosixPath("/var/cache") / cache_dir), (
        f"NUMBA_CACHE_DIR={numba!r} must be under CacheDirectory={cache_dir}"
    )


def test_daemon_needs_the_can_link(units):
    unit = units["ptw-rt.service"]["Unit"]
    assert "ptw-rt-can0.service" in " ".join(unit.get("Requires", []) + unit.get("BindsTo", []))
    assert "ptw-rt-can0.service" in " ".join(unit.get("After", []))
    assert units["ptw-rt.service"]["Install"]["WantedBy"] == ["multi-user.target"]


def test_can0_link_500k(units):
    service = units["ptw-rt-can0.service"]["Service"]
    commands = [shlex.split(v.lstrip("-@:+!")) for v in service["ExecStart"]]
    can = [c for c in commands if "bitrate" in c]
    assert len(can) == 1, commands
    assert can[0][can[0].index("bitrate") + 1] == "500000"
    assert "can0" in can[0] and ["type", "can"] == can[0][can[0].index("type") : can[0].index("type") + 2]
    assert any(c[-2:] == ["can0", "up"] for c in commands)
    assert _one(service, "Type") == "oneshot" and _one(service, "RemainAfterExit") == "yes"


def test_vcan0_bench_unit(units):
    service = units["ptw-rt-vcan0.service"]["Service"]
    text = " ".join(service["ExecStart"])
    assert "vcan0 type vcan" in text and "vcan0 up" in text
    assert _one(service, "Type") == "oneshot" and _one(service, "RemainAfterExit") == "yes"


def _stub_missing_executables(src: Path, dst: Path, stub: Path) -> list[str]:
    """Copy a unit, replacing Exec*= programs this machine does not have (e.g. /opt/ptw-rt/.venv/bin/ptw-rt on a
    dev box) by an executable stub, so verify checks the unit and not what is installed here."""
    replaced = []
    lines = []
    for line in src.read_text(encoding="utf-8").splitlines():
        key, sep, value = line.partition("=")
        if sep and key.strip() in EXEC_KEYS and value.strip():
            stripped = value.strip()
            prefix = stripped[: len(stripped) - len(stripped.lstrip("-@:+!|"))]
            program, _, rest = stripped[len(prefix) :].partition(" ")
            if not os.access(program, os.X_OK):
                replaced.append(program)
                line = f"{key}={prefix}{stub} {rest}".rstrip()
        lines.append(line)
    dst.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return replaced


def test_systemd_analyze_verify(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not found (install systemd) - unit files checked by the parser tests only")
    stub = tmp_path / "stub"
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    replaced = {}
    for name in UNITS:
        replaced[name] = _stub_missing_executables(SYSTEMD_DIR / name, tmp_path / name, stub)
    proc = subprocess.run(
        [analyze, "verify", "--man=no", *(str(tmp_path / name) for name in UNITS)],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=tmp_path,
    )
    output = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 0 and output == "", f"systemd-analyze verify (stubbed: {replaced}):\n{output}"


LINK_UNITS = ("ptw-rt-can0.service", "ptw-rt-vcan0.service")


@pytest.mark.parametrize("name", LINK_UNITS)
def test_link_units_hardened(units, name):
    """The CAN link units run ip(8) unprivileged with CAP_NET_ADMIN alone, sandboxed like the daemon."""
    service = units[name]["Service"]
    assert _one(service, "User") not in ("", "root", "0")
    assert _one(service, "AmbientCapabilities").split() == ["CAP_NET_ADMIN"]
    assert _one(service, "CapabilityBoundingSet").split() == ["CAP_NET_ADMIN"]
    for key in (
        "NoNewPrivileges",
        "ProtectHome",
        "PrivateTmp",
        "PrivateDevices",
        "ProtectKernelModules",
        "ProtectKernelTunables",
        "ProtectKernelLogs",
        "ProtectControlGroups",
        "ProtectClock",
        "RestrictNamespaces",
        "RestrictSUIDSGID",
        "MemoryDenyWriteExecute",
        "LockPersonality",
    ):
        assert _one(service, key) == "yes", key
    assert _one(service, "ProtectSystem") == "strict"
    assert set(_one(service, "RestrictAddressFamilies").split()) == {"AF_NETLINK", "AF_UNIX"}
    assert _one(service, "SystemCallFilter") == "@system-service"
    # a namespace of its own would configure that namespace's links, not the host's
    assert service.get("PrivateNetwork", ["no"])[-1] != "yes"
    assert service.get("PrivateUsers", ["no"])[-1] != "yes"
    assert not any("modprobe" in v for v in service["ExecStart"]), "the kernel autoloads vcan (rtnl-link-vcan)"


def _exposure(analyze: str, unit: Path) -> float | None:
    proc = subprocess.run(
        [analyze, "security", "--offline=yes", "--no-pager", str(unit)], capture_output=True, text=True, timeout=30
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", proc.stdout + proc.stderr)
    return float(m.group(1)) if m else None


@pytest.mark.parametrize("name", UNITS)
def test_systemd_analyze_security_exposure(name):
    """`systemd-analyze security --offline=yes` (systemd >= 250): every unit at the daemon's level, at most 2.0
    (systemd/README.md lists the figures)."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not found")
    score = _exposure(analyze, SYSTEMD_DIR / name)
    if score is None:
        pytest.skip("this systemd-analyze has no offline security analysis")
    assert score <= 2.0, f"{name}: exposure {score}"
