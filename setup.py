"""setuptools hook: cffi_modules cannot be declared in pyproject.toml.

The C core (estop._core) is built only with ESTOP_BUILD_CORE=1 (make setup); without it the
package is pure Python (pyext/estop_build_backend.py)."""

import os

from setuptools import setup

if os.environ.get("ESTOP_BUILD_CORE") == "1":
    setup(cffi_modules=["pyext/build_core.py:ffibuilder"])
else:
    setup()
