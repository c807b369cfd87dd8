#!/bin/sh
# One vcan0 session for tests/test_vcan_integration.py: the real daemon on a real SocketCAN vcan0.
#
# Runs either as PID 1 of a User-Mode Linux VM (init=THIS on the kernel command line; the host's root file
# system mounted through hostfs) or, on a kernel with CAN, as an ordinary root process on the host.
# All the work happens here; the pytest module only prepares the inputs and asserts on the files written.
#
# Input: a shell env file, session.env next to this script (pytest copies the script into the results
# directory), or the file named by PTW_VCAN_ENV (put on the kernel command line, which the kernel hands to
# init as its environment; or set by pytest in native mode). It defines:
#   RESULTS        directory for everything this script writes (on the host file system)
#   REPO           repository root (config/scooter.yaml is copied from there)
#   PTW_RT         absolute path of the venv's ptw-rt
#   RIDE_LOG       candump -L log of the simulated ride (channel vcan0)
#   SILENT_LOG     the same ride with the steering encoder silent for a window
#   STARTUP_TIMEOUT  seconds to wait for the daemon's first output frame
# Output (in RESULTS): candump.log (everything on vcan0, candump -L), daemon.stderr, daemon.stdout,
#   daemon.yaml (its config), cangen.txt and cangen_ext.txt (the random frames sent), marks.txt
#   ("name realtime" phase marks, same clock as candump's stamps), status.env (exit statuses), vm.txt (what a
#   system call costs in the VM, before the daemon starts and after it exits),
#   session.log (this script's trace), probe.txt (cyclictest -v: the VM's own 100 Hz timer lateness, when
#   rt-tests is installed; its first loop is due 10 ms after the probe_start mark), done (written last).

PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export PATH
umask 022

IS_INIT=0
[ "$$" = 1 ] && IS_INIT=1

finish() {
    sync
    if [ "$IS_INIT" = 1 ]; then
        halt -f || poweroff -f || echo o >/proc/sysrq-trigger
        sleep 5
    fi
}

if [ "$IS_INIT" = 1 ]; then
    mount -t proc proc /proc
    mount -t sysfs sys /sys
    mount -t tmpfs tmpfs /run 2>/dev/null || true
    export HOME=/root LANG=C.UTF-8
fi

[ -n "${PTW_VCAN_ENV:-}" ] || PTW_VCAN_ENV="$(dirname "$0")/session.env"
if [ ! -r "$PTW_VCAN_ENV" ]; then
    echo "vcan_session: PTW_VCAN_ENV not set or unreadable: '${PTW_VCAN_ENV:-}'" >&2
    finish
    exit 2
fi
# shellcheck disable=SC1090
. "$PTW_VCAN_ENV"
# the numba cache the host warmed (the guest's HOME is /root, whatever the host user's is): without it the daemon
# would compile the estimator inside the VM, slower than the start-up timeout on a fresh install
if [ -n "${NUMBA_CACHE_DIR:-}" ]; then export NUMBA_CACHE_DIR; fi

LOG="$RESULTS/session.log"
STATUS="$RESULTS/status.env"
MARKS="$RESULTS/marks.txt"
: >"$LOG"
: >"$STATUS"
: >"$MARKS"
: >"$RESULTS/vm.txt"

note() { echo "vcan_session: $*" | tee -a "$LOG"; }
status() { echo "$1=$2" >>"$STATUS"; }
mark() { echo "$1 $(date +%s.%N)" >>"$MARKS"; }
# what one system call costs here, in ns: 10,000 of dd's (read /dev/zero, write /dev/null; nothing leaves the VM).
# Natively well under a microsecond; inside User-Mode Linux every one is a round trip through the host (ptrace),
# which is what decides whether the VM can carry the session's traffic in real time at all.
# (dd's own "copied, S s": the copy loop alone, not the start of the processes around it)
syscall_ns() {
    dd if=/dev/zero of=/dev/null bs=1 count=5000 2>&1 |
        awk '/copied/ { for (i = 1; i < NF; i++) if ($(i + 1) == "s," || $(i + 1) == "s") s = $i } END { printf "%d\n", s * 1e9 / 10000 }'
}

session() {
    # ---- the CAN stack and vcan0
    if [ "$IS_INIT" = 1 ]; then
        kver=$(uname -r)
        mods=/usr/lib/uml/modules/$kver/kernel
        for m in net/can/can.ko net/can/can-raw.ko net/can/can-bcm.ko drivers/net/can/dev/can-dev.ko \
            drivers/net/can/vcan.ko; do
            if ! insmod "$mods/$m" >>"$LOG" 2>&1; then
                note "insmod $m failed"
                status MODULES_RC 1
                return 1
            fi
        done
        status MODULES_RC 0
    else
        modprobe vcan >>"$LOG" 2>&1 || true
        status MODULES_RC 0
    fi
    created=0
    if [ ! -e /sys/class/net/vcan0 ]; then
        if ! ip link add dev vcan0 type vcan >>"$LOG" 2>&1; then
            note "cannot create vcan0"
            status VCAN_RC 1
            return 1
        fi
        created=1
    fi
    ip link set up vcan0 >>"$LOG" 2>&1
    status VCAN_RC $?
    status VCAN_CREATED $created
    ip -details link show vcan0 >>"$LOG" 2>&1

    echo "syscall_ns_before $(syscall_ns)" >>"$RESULTS/vm.txt"

    # ---- priorities as on the vehicle: the daemon at SCHED_FIFO 40 (systemd/ptw-rt.service), the sensors and the
    # other nodes' traffic (canplayer, cangen) just above it (they are other ECUs, which the daemon never delays;
    # the same split as `ptw-rt bench`), the recorder below both: it reads the kernel's receive time stamps from a
    # large buffer, so being late costs it nothing. Without permission to set them, everything runs as it is.
    NODE=
    if chrt -f 41 true 2>/dev/null; then NODE="chrt -f 41"; fi

    # ---- the daemon's config: the vehicle's config with this bus, the loop's priority and a state file in RESULTS
    sed -e 's|^\(    interface:\).*|\1 socketcan|' \
        -e '/^runtime:$/a\  realtime:' -e '/^runtime:$/a\    priority: 40' \
        -e 's|^\(    channel:\).*|\1 vcan0|' \
        -e "s|^\(  state_file:\).*|\1 $RESULTS/state.json|" \
        "$REPO/config/scooter.yaml" >"$RESULTS/daemon.yaml"

    # ---- the VM's own timing, independent of the daemon: a 100 Hz timer at SCHED_FIFO 99 (above anything of the
    # session) for the whole session, each wake-up's lateness in us. When the host starves the VM, this probe is
    # late too; when it is on time and the daemon is not, the daemon is to blame (tests judge timing on that).
    probe_pid=
    if command -v cyclictest >/dev/null 2>&1; then
        mark probe_start
        cyclictest -p 99 -i 10000 -d 0 -m -v >"$RESULTS/probe.txt" 2>>"$LOG" &
        probe_pid=$!
    else
        note "no cyclictest (apt: rt-tests): timing judged without the VM probe"
    fi

    # ---- record everything on the bus (a 16 MiB receive buffer, so that a stalled candump loses nothing; -d counts
    # whatever the kernel still dropped on its socket, so a lost frame is the capture's and says so)
    candump -L -d -r 16777216 vcan0 >"$RESULTS/candump.log" 2>"$RESULTS/candump.stderr" &
    candump_pid=$!
    mark candump_started

    # ---- the daemon, stopped with SIGTERM below (--duration only as a safety net)
    mark daemon_start
    "$PTW_RT" run --config "$RESULTS/daemon.yaml" --interface socketcan --channel vcan0 \
        --state-file "$RESULTS/state.json" --duration 600 \
        >"$RESULTS/daemon.stdout" 2>"$RESULTS/daemon.stderr" &
    daemon_pid=$!

    # publishing: its first EST_Roll frame (0x300) on vcan0
    timeout "$STARTUP_TIMEOUT" candump -n 1 vcan0,300:7FF >/dev/null 2>>"$LOG"
    ready_rc=$?
    status READY_RC $ready_rc
    mark daemon_ready
    if [ "$ready_rc" != 0 ] || ! kill -0 "$daemon_pid" 2>/dev/null; then
        note "daemon not publishing (candump rc $ready_rc)"
        kill -TERM "$daemon_pid" 2>/dev/null
        wait "$daemon_pid"
        status DAEMON_RC $?
        kill -INT "$candump_pid" 2>/dev/null
        wait "$candump_pid"
        if [ -n "$probe_pid" ]; then kill -INT "$probe_pid" 2>/dev/null; wait "$probe_pid"; fi
        return 1
    fi
    sleep 1  # a second with no inputs: stale, FAULT

    # ---- the ride as logged, then the ride with a silent steering encoder
    mark play1_start
    $NODE canplayer -I "$RIDE_LOG" >>"$LOG" 2>&1
    status PLAY1_RC $?
    mark play1_end
    sleep 0.5
    mark play2_start
    $NODE canplayer -I "$SILENT_LOG" >>"$LOG" 2>&1
    status PLAY2_RC $?
    mark play2_end
    sleep 0.5

    # ---- random traffic (ids, lengths, payloads) while the daemon runs, then a quiet stretch
    mark cangen_start
    # -v: what was sent, so the host can tell these frames from the daemon's (random ids hit 0x300..0x311 too)
    $NODE cangen vcan0 -g 1 -n 2000 -v >"$RESULTS/cangen.txt" 2>>"$LOG"
    status CANGEN_RC $?
    $NODE cangen vcan0 -g 1 -n 500 -e -v >"$RESULTS/cangen_ext.txt" 2>>"$LOG"
    status CANGEN_EXT_RC $?
    mark cangen_end
    sleep 2

    # ---- clean stop
    mark sigterm
    kill -TERM "$daemon_pid"
    wait "$daemon_pid"
    status DAEMON_RC $?
    mark daemon_exited
    echo "syscall_ns_after $(syscall_ns)" >>"$RESULTS/vm.txt"
    sleep 0.2
    kill -INT "$candump_pid"
    wait "$candump_pid"
    status CANDUMP_RC $?
    if [ -n "$probe_pid" ]; then
        kill -INT "$probe_pid"
        wait "$probe_pid"
        status PROBE_RC $?
    fi
    if [ "$IS_INIT" != 1 ] && [ "$created" = 1 ]; then
        ip link del dev vcan0 >>"$LOG" 2>&1
    fi
    return 0
}

session
status SESSION_RC $?
echo ok >"$RESULTS/done"
note "session done"
finish
exit 0
