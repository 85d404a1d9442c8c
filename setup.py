"""Build the optional C speed-ups; fieldbus and its emulators work without them (Python paths)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "fieldbus._codec", sources=["fieldbus/_codec.c"], optional=True, extra_compile_args=["-O2"]
        ),
        Extension(
            "sim_slaves._dcloop", sources=["sim_slaves/_dcloop.c"], optional=True, extra_compile_args=["-O2"]
        ),
        Extension(
            "sim_slaves._pdlink", sources=["sim_slaves/_pdlink.c"], optional=True, extra_compile_args=["-O2"]
        ),
        Extension(
            "sim_slaves._motion",
            sources=["sim_slaves/_motion.c"],
            optional=True,
            extra_compile_args=["-O2", "-ffp-contract=off"],
        ),
    ]
)
