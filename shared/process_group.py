"""Stopping a process started in its own session (``start_new_session=True``) with its children."""

from __future__ import annotations

import os
import signal
import subprocess


def stop_group(proc: subprocess.Popen, grace_s: float) -> None:
    """SIGINT to ``proc``'s process group (a clean stop: `xm up` stops its services), SIGKILL to
    the group if it has not exited within ``grace_s`` seconds."""
    try:
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    except ProcessLookupError:
        pass
