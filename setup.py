"""Build the compiled kernels; everything else is in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[# (no fused multiply-adds either: its AVX2 and baseline builds agree to the bit
                   # whatever CFLAGS say, -march=native included)
                   Extension("segsnake._sampling", ["segsnake/_sampling.c"],
                             extra_compile_args=["-ffp-contract=off"]),
                   # (no fused multiply-adds: numpy's products, to the bit)
                   Extension("segsnake._flux", ["segsnake/_flux.c"],
                             extra_compile_args=["-ffp-contract=off"]),
                   # (no fused multiply-adds: the scan's ties are decided alike everywhere)
                   Extension("segsnake._scan", ["segsnake/_scan.c"],
                             extra_compile_args=["-ffp-contract=off"])])
