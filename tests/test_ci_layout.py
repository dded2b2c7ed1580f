"""What ``.ci/run`` relies on about the test tree and the README.

CI runs the README's test command, then collects only ``tests/test_vcan_*.py`` inside the vcan VM
(collecting the whole tree under software CPU emulation costs minutes). A vcan test written in any
other file would be skipped on the host and never collected in the VM: it would never run.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"


def test_every_vcan_test_lives_where_the_vm_collects() -> None:
    marks_vcan = re.compile(r"mark\.vcan|requires_vcan|vcan_channel")
    outside = [p.name for p in TESTS.glob("test_*.py")
               if not p.name.startswith("test_vcan_") and p != Path(__file__) and marks_vcan.search(p.read_text())]
    assert outside == [], f"vcan tests outside tests/test_vcan_*.py, which the VM stage never collects: {outside}"
    assert "tests/test_vcan_*.py" in (ROOT / ".ci" / "run").read_text()


def test_ci_runs_the_readmes_test_command() -> None:
    readme_lines = (ROOT / "README.md").read_text().splitlines()
    fence = readme_lines.index("```sh")
    test_command = readme_lines[fence + 2]
    assert "pytest" in test_command
    assert test_command in (ROOT / ".ci" / "run").read_text().splitlines()
