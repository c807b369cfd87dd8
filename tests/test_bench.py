"""The bench's figures are the measured process's own."""

from __future__ import annotations

import json
import subprocess
import sys

from ptw_rt.apps.bench import PEAK_RSS_MB


def test_peak_rss_is_the_childs_own_not_the_parents_carried_across_exec():
    held = bytearray(400 * 1024 * 1024)  # touched: resident in this (the parent) process
    for i in range(0, len(held), 4096):
        held[i] = 1
    code = f"import json; print(json.dumps({{'rss_mb': {PEAK_RSS_MB}}}))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    child = json.loads(out)["rss_mb"]
    assert 1.0 < child < 100.0, child  # a bare interpreter: ~10 MB; the parent's peak would read >= 400 MB
    del held
