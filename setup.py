"""setuptools hook: cffi_modules cannot be declared in pyproject.toml."""

from setuptools import setup

setup(cffi_modules=["pyext/build_core.py:ffibuilder"])
