"""Run Python as an install without the ``mf4`` extra would: ``import asammdf`` fails.

python-can imports asammdf (and with it pandas and sympy) on ``import can`` whenever it is
installed, for its MF4 reader.  Under the VM's software CPU emulation that import takes about
half a minute per process, and the vcan tests start several processes (``socd run``, ``socd
replay``) that read CSV recordings only.  ``.ci/run`` puts this directory on PYTHONPATH for the VM
stage, so those processes start as they would in the package's default install.
"""

import sys

sys.modules["asammdf"] = None  # type: ignore[assignment]  # makes `import asammdf` raise ImportError
