"""Tests marked ``own_process`` run in a pytest process of their own (issue 17).

Ray's core worker is made once per process: ``ray.init`` after ``ray.shutdown`` in one
process, or a shutdown while another thread still waits on Ray, leaves objects that point
into freed core-worker state, and the process crashes later — often only at exit, after
every test has passed (SIGSEGV in ``_raylet.so``). So the pytest process never starts Ray
(a guard in conftest fails a test that does: ``ray_was_started_here``), and each test that needs Ray in-process is handed
to a child ``python -m pytest <nodeid>``. The child's exit status is part of the result:
a child that ends in a signal fails the test even when the test itself passed, which is
how a crash at exit shows up as a failure instead of passing unseen.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
from _pytest.reports import TestReport

from mining.pipeline.failures import exit_reason

MARKER = "own_process"
CHILD_ENV = "TUBE_MINER_OWN_PROCESS"  # set in the child: run the test here, do not hand it on
CHILD_TIMEOUT_S = 1200  # one test; a hung child fails rather than hangs the suite


def in_child() -> bool:
    return os.environ.get(CHILD_ENV) == "1"


def _outcome(xml_path: Path) -> tuple[str, str]:
    """(passed | failed | skipped, message) of the one test case in a JUnit XML report."""
    if not xml_path.exists():
        return "failed", "the child wrote no report"
    cases = ET.parse(xml_path).getroot().iter("testcase")
    case = next(cases, None)
    if case is None:
        return "failed", "the child ran no test (was the node id collected?)"
    for tag in ("failure", "error"):
        el = case.find(tag)
        if el is not None:
            return "failed", (el.get("message") or "") + "\n" + (el.text or "")
    el = case.find("skipped")
    if el is not None:
        return "skipped", el.get("message") or "skipped"
    return "passed", ""


def run_in_own_process(item: pytest.Item) -> list[TestReport]:
    """Run ``item`` in a child pytest; its setup and call reports for this process (the
    teardown is this process's own: see ``protocol``)."""
    base = item.config._tmp_path_factory.mktemp("own-process")  # noqa: SLF001 - the session's temp root
    xml = base / "report.xml"
    env = dict(os.environ, **{CHILD_ENV: "1"})
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(item.config.rootpath),
           f"--basetemp={base / 'tmp'}", f"--junitxml={xml}", "-o", "junit_logging=no", item.nodeid]
    t0 = time.time()
    try:
        p = subprocess.run(cmd, cwd=item.config.rootpath, env=env, capture_output=True, text=True,
                           timeout=CHILD_TIMEOUT_S)
        rc, output = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as e:
        rc, output = None, f"{e.stdout or ''}{e.stderr or ''}"
    t1 = time.time()
    outcome, message = _outcome(xml)
    tail = "\n".join(output.splitlines()[-60:])
    if rc is None:
        outcome, message = "failed", f"the test's own process did not end within {CHILD_TIMEOUT_S} s"
    elif rc < 0:
        # the point of the marker: a crash after the test passed is a failure too
        outcome = "failed"
        message = f"the test's own process ended in {exit_reason(rc)} (test outcome there: {_outcome(xml)[0]})\n{message}"
    elif outcome == "passed" and rc != 0:
        outcome, message = "failed", f"the test passed but its own process ended with {exit_reason(rc)}"
    keywords: dict[str, Any] = {k: 1 for k in item.keywords}
    sections = [("Captured output of the test's own process", tail)] if output else []

    def report(when: str, result: str, longrepr: Any = None, duration: float = 0.0) -> TestReport:
        return TestReport(item.nodeid, item.location, keywords, result, longrepr, when, sections if when == "call" else (),
                          duration, t0, t1)

    if outcome == "skipped":
        path, line, _ = item.location
        return [report("setup", "skipped", (str(path), (line or 0) + 1, message))]
    longrepr = None if outcome == "passed" else f"[{exit_reason(rc) if rc is not None else 'timeout'}] {message.strip()}"
    return [report("setup", "passed"), report("call", outcome, longrepr, t1 - t0)]


def ray_was_started_here() -> bool:
    """Whether this process started (or joined) Ray as a driver, now or at any time before.

    ``ray.shutdown`` leaves the driver's GCS error subscriber on Ray's global worker (Ray
    2.58; tests/test_ray_exit.py checks that this still detects a test that starts Ray)."""
    ray = sys.modules.get("ray")
    if ray is None:
        return False
    from ray._private import worker

    return ray.is_initialized() or hasattr(worker.global_worker, "gcs_error_subscriber")


RAY_IN_PYTEST = ("this test started Ray in the pytest process: restarting Ray in one process crashes Ray's core "
                 f"at exit. Mark it @pytest.mark.{MARKER} (tests/_own_process.py), or run Ray in a subprocess")


def protocol(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    """pytest's run-test protocol for an ``own_process`` item: the child's setup and call
    reports, then this process's own teardown up to ``nextitem``, as pytest's protocol does:
    module and session fixtures that earlier items set up here are torn down when the next
    item no longer needs them (without it, the next module's setup fails with "previous item
    was not torn down properly"). Only the setup stack is torn down: the item itself was
    never set up here, so the teardown hooks (which expect what setup stashed) are not run."""
    item.ihook.pytest_runtest_logstart(nodeid=item.nodeid, location=item.location)
    reports = run_in_own_process(item)
    for report in reports:
        item.ihook.pytest_runtest_logreport(report=report)
    try:
        item.session._setupstate.teardown_exact(nextitem)  # noqa: SLF001 - what pytest_runtest_teardown does
        outcome, longrepr = "passed", None
    except Exception as e:  # noqa: BLE001 - a fixture's teardown failed: reported like pytest would
        outcome, longrepr = "failed", f"teardown of fixtures before {nextitem.nodeid if nextitem else 'the end'}: {e!r}"
    item.ihook.pytest_runtest_logreport(report=TestReport(
        item.nodeid, item.location, {k: 1 for k in item.keywords}, outcome, longrepr, "teardown"))
    item.ihook.pytest_runtest_logfinish(nodeid=item.nodeid, location=item.location)
