"""The suite's wait for a process's output (conftest.wait_for_output): a line is seen when it is
written, whatever else the same write or read carried."""
import signal
import subprocess
import sys
import time

import pytest

from conftest import killed_on_exit, stop, wait_for_output

# two lines in one write, then nothing for 30 s, then a last line
BURST = ("import sys, time\n"
         "sys.stdout.write('zero set\\nactivated\\n'); sys.stdout.flush()\n"
         "time.sleep(30)\n"
         "print('done', flush=True)\n")


def _python(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def test_a_line_written_with_the_one_before_it_is_seen_at_once():
    proc = _python(BURST)
    with killed_on_exit(proc):
        start = time.monotonic()
        seen = wait_for_output(proc, "activated", timeout=10.0)
        waited = time.monotonic() - start
        rest = stop(proc, signal.SIGKILL, 10)
    assert waited < 5.0, f"seen after {waited:.1f} s"
    assert seen == "zero set\nactivated\n" and rest == ""


def test_a_later_wait_finds_a_line_an_earlier_one_read_past_and_nothing_is_lost():
    proc = _python(BURST)
    with killed_on_exit(proc):
        first = wait_for_output(proc, "zero set", timeout=10.0)
        second = wait_for_output(proc, "activated", timeout=10.0)
        rest = stop(proc, signal.SIGKILL, 10)
    assert first == "zero set\nactivated\n"       # one read carried both lines
    assert second == ""                            # found in what the first read past its line
    assert first + second + rest == "zero set\nactivated\n"


def test_the_rest_of_the_output_follows_what_was_read():
    proc = _python("print('a'); print('b'); print('c')")
    with killed_on_exit(proc):
        seen = wait_for_output(proc, "a", timeout=10.0)
        rest = proc.communicate(timeout=10)[0]
    assert seen + rest == "a\nb\nc\n"


def test_a_line_that_never_comes_fails_the_wait_on_time_with_the_output():
    proc = _python("print('up', flush=True); import time; time.sleep(30)")
    with killed_on_exit(proc):
        start = time.monotonic()
        with pytest.raises(AssertionError, match="'ready' not seen within 1 s; output:\nup\n"):
            wait_for_output(proc, "ready", timeout=1.0)
        assert time.monotonic() - start < 5.0
        stop(proc, signal.SIGKILL, 10)


def test_a_process_that_ends_fails_the_wait_with_what_it_said():
    proc = _python("print('bye', end='')")
    with killed_on_exit(proc):
        with pytest.raises(AssertionError, match="output:\nbye"):
            wait_for_output(proc, "ready", timeout=10.0)
        proc.wait(timeout=10)
