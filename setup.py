"""Build the compiled kernels; everything else is in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("segsnake._sampling", ["segsnake/_sampling.c"]),
                   Extension("segsnake._winding", ["segsnake/_winding.c"])])
