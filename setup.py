"""Build the optional C codec; fieldbus works without it (numpy path)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "fieldbus._codec", sources=["fieldbus/_codec.c"], optional=True, extra_compile_args=["-O2"]
        ),
    ]
)
