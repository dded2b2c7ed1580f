"""`socd run` imports only what the daemon uses: never scipy, matplotlib, pandas or asammdf.

A fresh interpreter goes the way ``socd run --config default.toml`` goes — the CLI with every
subcommand registered, the packaged config loaded, the :class:`Daemon` built (bus, estimator,
Zenoh publisher) — and its ``sys.modules`` is read.  python-can's ``import can`` itself loads
asammdf (and with it pandas) whenever they are installed, as they are where the ``mf4`` extra
is (tests/test_wheel.py checks the plain install, where they are not); so those two are held
to what ``import can`` alone loads in this environment.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: never on the daemon's import path, whatever is installed
NEVER = ("scipy", "matplotlib", "pybamm", "tomli_w")
#: only as far as `import can` pulls them in by itself (python-can's optional MF4 support)
ONLY_VIA_CAN = ("pandas", "asammdf")

DAEMON_IMPORTS = """
import json, sys
from service.cli import build_parser
args = build_parser().parse_args(["run", "--config", "default.toml"])
from service.config import load_config
from service.daemon.daemon import Daemon
config = load_config(args.config)
daemon = Daemon(config)
print(json.dumps(sorted(m for m in sys.modules if "." not in m)))
"""


def _top_level_modules(code: str, cwd: Path) -> set[str]:
    done = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True,
                          timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def test_socd_run_imports_no_research_or_plotting_libraries(tmp_path: Path) -> None:
    loaded = _top_level_modules(DAEMON_IMPORTS, tmp_path)
    assert {"service", "can", "cantools", "numpy", "pydantic"} <= loaded  # it did build
    assert not loaded & set(NEVER), sorted(loaded & set(NEVER))
    by_can = _top_level_modules('import can, json, sys; print(json.dumps(sorted(sys.modules)))', tmp_path)
    extra = (loaded & set(ONLY_VIA_CAN)) - by_can
    assert not extra, f"socd itself imports {sorted(extra)}"


#: ``socd CMD --help`` run in a fresh interpreter; prints the top-level modules it loaded
COMMAND_HELP_IMPORTS = """
import contextlib, io, json, sys
from service.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    code = main([{command!r}, "--help"])
assert code == 0, code
print(json.dumps(sorted(m for m in sys.modules if "." not in m)))
"""


@pytest.mark.parametrize("command", ["evaluate", "fit", "diagnose"])
def test_the_offline_commands_do_not_load_python_can(tmp_path: Path, command: str) -> None:
    """Only the named command's parser is built: ``socd run``'s and ``socd replay``'s import
    python-can, whose ``import can`` loads asammdf and pandas where the ``mf4`` extra is
    installed (as here), a second or two at every start of a command that reads CSV files."""
    loaded = _top_level_modules(COMMAND_HELP_IMPORTS.format(command=command), tmp_path)
    assert "service" in loaded
    assert not loaded & {"can", "asammdf"}, sorted(loaded & {"can", "asammdf"})


def test_the_named_command_is_the_first_word_that_is_not_a_flag() -> None:
    from service.cli import build_parser, named_command

    assert named_command(["evaluate", "--cell", "x.toml", "run"]) == "evaluate"
    assert named_command(["--help"]) is None and named_command(["-h", "evaluate"]) is None
    assert named_command(["evaluat"]) is None and named_command([]) is None
    sub = next(a for a in build_parser("fit")._actions if hasattr(a, "choices") and a.choices)
    assert list(sub.choices) == ["fit"]
