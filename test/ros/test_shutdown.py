"""``ros.shutdown``: a stop signal after the node closed does not change the exit code."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from ros_helpers import ROOT

SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, time
    from mfp_mapper.ros.shutdown import SpinUntilSignal
    with SpinUntilSignal(print, keep_after_exit={keep}) as stopper:
        os.kill(os.getpid(), signal.SIGINT)  # the stop: the node closes, the map is saved
        time.sleep(0.1)
        assert stopper.stop.is_set()
    os.kill(os.getpid(), signal.SIGTERM)  # launch's SIGTERM, after the save, before the end
    time.sleep(0.2)
    sys.exit(0)
    """
)


def _run(keep: bool) -> int:
    script = SCRIPT.format(keep=keep)
    return subprocess.run([sys.executable, "-c", script], cwd=ROOT, timeout=60).returncode


def test_a_sigterm_after_the_save_exits_0() -> None:
    assert _run(keep=True) == 0


def test_without_keep_after_exit_the_previous_handler_comes_back() -> None:
    assert _run(keep=False) == -15  # what the node's main() did before
