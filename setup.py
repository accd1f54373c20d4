"""The package's one compiled part: ``spdslam/geometry/_kernels.c``, optional (without a C
compiler the install goes on and spdslam uses its NumPy code; docs/install.md). Everything
else is in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("spdslam.geometry._kernels", ["spdslam/geometry/_kernels.c"], optional=True,
                  extra_compile_args=["-O3"]),
    ],
)
