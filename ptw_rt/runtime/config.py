"""The daemon's own section of the config file (`runtime:`): bus, timeouts, persisted state, logs, real time.

Kept apart from the vehicle and tuning: changing the CAN channel must not
invalidate the design file, so this section is not part of the config hash.
"""

from __future__ import annotations

from typing import Any

from ptw_rt.runtime.realtime import REALTIME_SCHEMA
from ptw_rt.schema import Number, Section, Text

BUS_SCHEMA = Section(
    fields={},
    optional={
        "interface": (Text(doc="python-can interface: socketcan, virtual, ..."), "socketcan"),
        "channel": (Text(doc="e.g. can0, vcan0, or a virtual bus name"), "can0"),
        "bitrate": (Number("bit/s", integer=True, gt=0), 500000),
        "send_retries": (Number("", integer=True, ge=0, le=10), 1),
    },
)

GPS_SCHEMA = Section(
    fields={},
    optional={
        "source": (
            Text(choices=("can", "serial"), doc="can (GPS_Velocity frames) or serial (NMEA 0183 receiver)"),
            "can",
        ),
        "serial_port": (Text(doc="e.g. /dev/ttyACM0"), "/dev/ttyACM0"),
        "serial_baudrate": (Number("baud", integer=True, gt=0), 9600),
    },
)

RUNTIME_SCHEMA = Section(
    fields={},
    optional={
        "bus": (BUS_SCHEMA, BUS_SCHEMA.check("runtime.bus", {})),
        "gps": (GPS_SCHEMA, GPS_SCHEMA.check("runtime.gps", {})),
        # a message is stale after this many of its DBC cycle times without a valid frame
        "stale_after_periods": (Number("", gt=1, le=100), 3.0),
        "state_file": (Text(doc="learned tyre stiffness, saved atomically"), "/var/lib/ptw-rt/state.json"),
        "state_save_interval_s": (Number("s", gt=0), 60.0),
        "health_log_interval_s": (Number("s", gt=0), 10.0),
        "log_repeat_interval_s": (Number("s", ge=0), 5.0),
        "log_level": (Text(choices=("DEBUG", "INFO", "WARNING", "ERROR")), "INFO"),
        "realtime": (REALTIME_SCHEMA, REALTIME_SCHEMA.check("runtime.realtime", {})),
    },
)


def runtime_defaults() -> dict[str, Any]:
    return RUNTIME_SCHEMA.check("runtime", {})
