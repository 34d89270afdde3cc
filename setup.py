"""Build the compiled kernels; everything else is in pyproject.toml."""

from setuptools import Extension, setup

# Every kernel: the buffer checks they share, and no fused multiply-adds (_sampling's AVX2 and
# baseline builds agree to the bit whatever CFLAGS say, -march=native included; _flux gives
# numpy's products to the bit; _scan and _distance decide
# their ties alike everywhere).
KERNEL = {"depends": ["segsnake/_buffers.h"], "extra_compile_args": ["-ffp-contract=off"]}

setup(ext_modules=[Extension("segsnake._sampling", ["segsnake/_sampling.c"], **KERNEL),
                   Extension("segsnake._flux", ["segsnake/_flux.c"], **KERNEL),
                   Extension("segsnake._scan", ["segsnake/_scan.c"], **KERNEL),
                   Extension("segsnake._distance", ["segsnake/_distance.c"], **KERNEL)])
