"""The live viewer's run: it says when --realtime-rate is not reached, and its serve phase ends on
Ctrl-C or SIGTERM even when a script started it in the background (SIGINT ignored)."""

import os
import signal
import subprocess
import sys
import time

from safesysid.progress import realtime_shortfall

SERVE = """
from safesysid.progress import RunDisplay, serve_until_interrupt
class Viewer:
    def web_url(self):
        return "http://localhost:7000"
serve_until_interrupt(RunDisplay(meshcat=True, keep_serving=True, viewer=Viewer()))
print("stopped", flush=True)
"""


def test_a_rate_not_reached_is_said():
    assert realtime_shortfall(5.0, 10.0, 1.0).startswith("run: warning: --realtime-rate 1 not reached (0.50x)")
    assert realtime_shortfall(9.5, 10.0, 1.0) is None  # within 10 %
    assert realtime_shortfall(1.0, 10.0, 0.0) is None  # as fast as possible: nothing to reach


def test_serving_ends_on_ctrl_c_when_started_with_sigint_ignored():
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc = subprocess.Popen(
            [sys.executable, "-c", SERVE],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),  # as `cmd &` in a script
        )
        deadline = time.time() + 60
        while "Ctrl-C to quit" not in (line := proc.stderr.readline()) and time.time() < deadline:
            assert line, "the serve phase did not start"
        os.kill(proc.pid, sig)
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0 and "stopped" in out
