"""Build step: the per-sample path is compiled to C with mypyc; everything else is plain Python.

Why: the service's throughput target needs about 1.3× more than CPython runs this
code at, and mypyc gets it from the same typed sources, with no second implementation to
keep in step. The modules stay ordinary Python: ``GLIDER_HIL_PURE_PYTHON=1`` at install
time skips compilation and everything runs interpreted, with the same results to the bit
(``tests/test_compiled.py`` compares the two). ``GLIDER_HIL_INTERPRETED=1`` at run time
does the same for one process without reinstalling (``protocols/compiled.py``).

Floating point: ``-ffp-contract=off`` keeps the C compiler from fusing a·b + c into one
rounding (it may, for targets with FMA), so compiled arithmetic rounds exactly as CPython's.
``-Wno-tautological-compare``: mypyc's NaN checks are ``x != x``, which GCC 12 flags.
"""

from __future__ import annotations

import os
import sys

from setuptools import setup
from setuptools.command.build_ext import build_ext

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocols.compiled import ENV_PURE_PYTHON, flag, source_paths  # beside the run-time switch

FLOAT_FLAGS = ["-ffp-contract=off", "-Wno-tautological-compare"]


class BuildCompiledModules(build_ext):
    """build_ext that says what to do when the C compiler is missing or fails."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as error:  # CompileError, LinkError, a missing compiler: all fatal
            raise SystemExit(
                f"glider-hil: compiling the per-sample path failed ({error}).\n"
                "It needs a C compiler and the Python headers (Debian: apt-get install gcc "
                "python3-dev). Or install without compiling: GLIDER_HIL_PURE_PYTHON=1 "
                "pip install ... (the same code, interpreted, about 1.5x slower)."
            ) from error


def compiled_modules() -> list:
    if flag(ENV_PURE_PYTHON):
        return []
    from mypyc.build import mypycify

    extensions = mypycify(source_paths(), group_name="glider_hil_native", opt_level="3")
    for extension in extensions:
        extension.extra_compile_args = [*extension.extra_compile_args, *FLOAT_FLAGS]
    return extensions


setup(ext_modules=compiled_modules(), cmdclass={"build_ext": BuildCompiledModules})
