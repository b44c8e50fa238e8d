"""A process that ends in a signal is a failure, in the suite and in the `mine` commands (issue 17).

The test command used to crash at exit (SIGSEGV in Ray's core) after every test had passed:
the pytest process started and stopped Ray several times. Now the pytest process never
starts Ray (conftest's guard), tests that need Ray in-process are marked ``own_process``
and run in a pytest of their own whose exit status counts (tests/_own_process.py), and
each `mine` command starts Ray at most once per process. These tests check both halves:
that the machinery turns a crash at exit into a failure (so the check can fail), and that
the Ray-starting commands exit 0 run after run.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from _run import env, mine_cmd
from conftest import REPO

HERE = Path(__file__).resolve().parent

pytestmark = pytest.mark.slow  # child pytest processes, some with a local Ray

# A tiny synthetic job: 8 small frames, two windows.
TINY = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=8", "--option", "width=621",
        "--option", "height=188", "--set", "window.core=4", "--set", "window.context_before=2",
        "--set", "window.context_after=2"]

SUITE = '''
import atexit, os, signal
import pytest

@pytest.mark.own_process
def test_passes_then_crashes_at_exit():
    atexit.register(lambda: os.kill(os.getpid(), signal.SIGSEGV))

@pytest.mark.own_process
def test_passes_and_exits_cleanly():
    assert True

@pytest.mark.own_process
def test_fails_in_its_own_process():
    assert 1 == 2, "a real failure comes back"

@pytest.mark.own_process
def test_skips_in_its_own_process():
    pytest.skip("nothing to do here")

def test_starts_ray_in_the_pytest_process():
    import ray
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    ray.shutdown()

def test_plain():
    assert True
'''


# A module whose own_process test follows a test that set up a module fixture here, then
# another module: the fixture must be torn down before the next module starts, as pytest does.
FIRST_MODULE = '''
import os
import pytest

@pytest.fixture(scope="module")
def resource():
    os.environ["RESOURCE_OPEN"] = "1"
    yield
    del os.environ["RESOURCE_OPEN"]

def test_uses_the_module_fixture(resource):
    assert os.environ["RESOURCE_OPEN"] == "1"

@pytest.mark.own_process
def test_last_of_its_module_in_its_own_process():
    assert True
'''

SECOND_MODULE = '''
import os

def test_the_previous_module_was_torn_down():
    assert "RESOURCE_OPEN" not in os.environ
'''

@pytest.fixture
def suite(tmp_path) -> Path:
    """A small test folder that uses this suite's conftest (the hook and the guard)."""
    d = tmp_path / "suite"
    d.mkdir()
    for name in ("conftest.py", "_own_process.py"):
        shutil.copy(HERE / name, d / name)
    (d / "test_cases.py").write_text(SUITE)
    return d


def _run_suite(suite: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", "--rootdir",
                           str(suite), *args, str(suite)], cwd=suite, env=env(), capture_output=True, text=True,
                          timeout=600)


def test_a_crash_at_exit_fails_the_test_and_a_clean_exit_passes(suite):
    p = _run_suite(suite, "-k", "own_process or exits_cleanly or crashes or fails_in or skips_in")
    out = p.stdout + p.stderr
    assert p.returncode == 1, out  # failures, but the outer pytest itself ends normally
    assert "FAILED test_cases.py::test_passes_then_crashes_at_exit" in out, out
    assert "signal SIGSEGV" in out, out
    assert "PASSED test_cases.py::test_passes_and_exits_cleanly" in out, out
    assert "FAILED test_cases.py::test_fails_in_its_own_process" in out and "a real failure comes back" in out, out
    assert "SKIPPED" in out and "nothing to do here" in out, out
    assert "2 failed, 1 passed, 1 skipped" in out, out


def test_a_test_that_starts_ray_in_the_pytest_process_fails(suite):
    p = _run_suite(suite, "-k", "starts_ray or plain")
    out = p.stdout + p.stderr
    assert p.returncode == 1, out
    # the guard fails the test at its teardown, naming the cause
    assert "ERROR test_cases.py::test_starts_ray_in_the_pytest_process" in out, out
    assert "started Ray in the pytest process" in out, out
    assert "2 passed, 4 deselected, 1 error" in out, out


def test_mine_submit_exits_0_run_after_run(tmp_path):
    # Each run starts (and stops) a local Ray of its own, in a fresh catalogue.
    for k in range(3):
        out = tmp_path / f"out{k}"
        p = subprocess.run(mine_cmd("submit", *TINY, "--workers", "1", "--no-progress", "--out", str(out)), cwd=REPO,
                           env=env(), capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, (k, p.returncode, p.stdout[-2000:], p.stderr[-3000:])
        assert "windows: 2 ok, 0 failed" in p.stdout, p.stdout


def test_an_own_process_test_at_a_modules_end_lets_its_fixtures_be_torn_down(suite):
    (suite / "test_cases.py").unlink()
    (suite / "test_m1.py").write_text(FIRST_MODULE)
    (suite / "test_m2.py").write_text(SECOND_MODULE)
    p = _run_suite(suite)
    out = p.stdout + p.stderr
    assert p.returncode == 0, out  # was: "previous item was not torn down properly" at the next module
    assert "3 passed" in out and "error" not in out.lower(), out
