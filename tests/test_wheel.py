"""The built package works on its own: ``python -m build`` (sdist, then the wheel from it), the
wheel installed with its core dependencies only in a fresh venv outside the checkout, and
``socd demo`` and ``socd replay`` of the shipped recording by its name run from an empty directory:
the packaged DBCs, profile and drive cycle, the generated-DBC import, the whole chain, the documents
the help and the demo cite, and no research or plotting library in the daemon.

Slow (a build, a venv and a pip install from the index; about a minute) and needs PyPI.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.wheel

ROOT = Path(__file__).resolve().parent.parent
DEMO_SECONDS = "5"


def _run(cmd: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    assert done.returncode == 0, f"{' '.join(cmd)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return done


def test_wheel_installed_in_a_fresh_venv_runs_the_demo(tmp_path: Path) -> None:
    dist, venv, work = tmp_path / "dist", tmp_path / "venv", tmp_path / "work"
    work.mkdir()
    _run([sys.executable, "-m", "build", "--outdir", str(dist), str(ROOT)], cwd=tmp_path, timeout=600)
    (wheel,) = dist.glob("socd-*.whl")
    _run([sys.executable, "-m", "venv", str(venv)], cwd=tmp_path, timeout=120)
    python, socd = venv / "bin" / "python", venv / "bin" / "socd"
    _run([str(python), "-m", "pip", "install", "--quiet", str(wheel)], cwd=tmp_path, timeout=600)

    # the demo, from a directory that has nothing of the checkout
    done = _run([str(socd), "demo", "--seconds", DEMO_SECONDS, "--cells", "100"], cwd=work, timeout=300)
    rmse = re.search(r"^SOC error vs truth: RMSE (\d+\.\d+) %", done.stdout, re.MULTILINE)
    assert rmse and float(rmse.group(1)) < 10.0, done.stdout
    assert "plot: not written (needs matplotlib, which is not installed: pip install 'socd[fit]')" in done.stdout

    # the documents socd's output cites are installed: the results the help texts cite, where
    # `socd --help` says, and the bundled drive's README, which the demo cites for its full start
    helped = " ".join(_run([str(socd), "--help"], cwd=work, timeout=60).stdout.split())
    results = re.search(r"is installed with socd: (\S+)/NAME\.md", helped)
    assert results and Path(results.group(1)).is_relative_to(venv), helped
    shipped = {p.name for p in Path(results.group(1)).iterdir()}
    assert {"tuning.md", "characterisation.md", "cell_options.md"} <= shipped
    assert {Path(name).suffix for name in shipped} == {".md"}, shipped  # not the research tool beside them
    assert "(service/data/README.md)" in done.stdout
    assert (Path(results.group(1)).parents[1] / "data" / "README.md").is_file()

    # the recording the package ships, named alone, replayed to a log
    done = _run([str(socd), "replay", "pan18650pf_25C_US06", "--no-send", "--cells", "2", "--record", "drive.asc"],
                cwd=work, timeout=120)
    assert "frames recorded to drive.asc, 0 failed" in done.stdout + done.stderr
    assert (work / "drive.asc").stat().st_size > 0

    # installed from the wheel, not imported from the checkout
    where = _run([str(python), "-c", "import service; print(service.__file__)"], cwd=work, timeout=60)
    assert Path(where.stdout.strip()).is_relative_to(venv)

    # the core install has no research or plotting library, and the daemon's path imports none
    modules = _run([str(python), "-c", (
        "import json, sys\n"
        "from service.config import load_config\n"
        "from service.daemon.daemon import Daemon\n"
        "Daemon(load_config('socketcan_can0.toml'))\n"
        "print(json.dumps(sorted(sys.modules)))"
    )], cwd=work, timeout=120)
    loaded = set(json.loads(modules.stdout.strip().splitlines()[-1]))
    assert not loaded & {"scipy", "matplotlib", "pandas", "asammdf", "pybamm"}
