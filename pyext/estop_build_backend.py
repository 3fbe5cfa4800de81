"""The build backend: setuptools, plus cffi when the C core is built (``ESTOP_BUILD_CORE=1``).

The tools (codecs, ``estop stop|status|release|lift|remote``) are pure Python and need no C
compiler; a plain ``pip install .`` installs just them. The cffi build of the core
(``estop._core``, what the tests and simulations use) is made only when asked for:
``ESTOP_BUILD_CORE=1 pip install -e '.[test]'`` (``make setup`` does). Only then does the
build environment get cffi, and setup.py declare the extension.
"""

from __future__ import annotations

import os

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403 - the whole PEP 517/660 interface

CORE_ENV = "ESTOP_BUILD_CORE"
_CORE_REQUIRES = ["cffi>=1.16"]


def _core() -> list[str]:
    return list(_CORE_REQUIRES) if os.environ.get(CORE_ENV) == "1" else []


def get_requires_for_build_wheel(config_settings=None):  # type: ignore[no-untyped-def]
    return _setuptools.get_requires_for_build_wheel(config_settings) + _core()


def get_requires_for_build_editable(config_settings=None):  # type: ignore[no-untyped-def]
    return _setuptools.get_requires_for_build_editable(config_settings) + _core()
