"""Types of the optional C module sim_slaves._pdlink (sim_slaves/_pdlink.c); absent where it is not built."""

import numpy as np
import numpy.typing as npt

def gather(
    memory: npt.NDArray[np.uint8],
    addrs: npt.NDArray[np.int64],
    rows: npt.NDArray[np.int64],
    kinds: bytes,
    arrays: tuple[npt.NDArray[np.int64], ...],
    /,
) -> None:
    """Each object's bytes in ``memory`` (little-endian, of its kind) -> its int64 array at the row's slot."""

def scatter(
    memory: npt.NDArray[np.uint8],
    addrs: npt.NDArray[np.int64],
    rows: npt.NDArray[np.int64],
    kinds: bytes,
    arrays: tuple[npt.NDArray[np.int64], ...],
    /,
) -> None:
    """Each int64 array's value at the row's slot -> the object's bytes in ``memory`` (its low bytes)."""
