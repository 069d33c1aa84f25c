"""Reader of the Silverbox benchmark records (data outside the package, never downloaded)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

__all__ = ["load_silverbox", "SILVERBOX_FS", "SILVERBOX_ARROW_END", "ENV_VAR"]

#: Sampling frequency of the Silverbox records, Hz (``10^7 / 2^14`` ≈ 610.35 Hz).
SILVERBOX_FS: float = 1e7 / 2**14

#: First sample of the multisine part of ``SNLS80mV.csv``; samples ``[0, 40700)`` are the arrow.
SILVERBOX_ARROW_END: int = 40_700

#: Environment variable naming the folder that holds ``SNLS80mV.csv``.
ENV_VAR = "TORCH_NSSM_SILVERBOX"

_REPO_ROOT = Path(__file__).resolve().parents[2]


@functools.lru_cache(maxsize=4)
def _read_silverbox_csv(path: str, mtime_ns: int) -> np.ndarray:
    with open(path, encoding="utf-8") as fh:
        header = fh.readline()
    names = [h.strip().strip('"') for h in header.strip().split(",")]
    try:
        cols = (names.index("V1"), names.index("V2"))
    except ValueError:
        raise ValueError(f"{path}: expected columns 'V1' and 'V2' in the header, got {names}") from None
    data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=cols, dtype=np.float64, ndmin=2)
    data.setflags(write=False)
    return data


def load_silverbox(
    path: str | os.PathLike[str] | None = None,
    part: str = "multisine",
    file: str = "SNLS80mV.csv",
) -> tuple[np.ndarray, np.ndarray]:
    """Read the Silverbox benchmark (Wigren & Schoukens 2013): input ``V1``, output ``V2``.

    The sampling frequency is :data:`SILVERBOX_FS` (``10^7 / 2^14`` Hz).  In ``SNLS80mV.csv``
    samples ``[0, 40700)`` are the "arrow" part (usual test set) and ``[40700, end)`` the
    multisine part (usual training set).  Other files (``Schroeder80mV.csv``) only have
    ``part="all"``.

    Parameters
    ----------
    path : str or path-like, optional
        Directory holding the CSV files.  Default: ``$TORCH_NSSM_SILVERBOX`` when set, otherwise
        ``../shared/data/silverbox`` relative to the current working directory, then relative
        to the repository root.
    part : {"multisine", "arrow", "all"}
        Which samples to return.
    file : str
        File name inside the directory.

    Returns
    -------
    u, y : ndarray, shape (N, 1)
        Input and output voltages, float64.

    Raises
    ------
    FileNotFoundError
        If the file is in none of the directories tried (listed in the message).
    ValueError
        If ``part`` is unknown, or not ``"all"`` for a file other than ``SNLS80mV.csv``.
    """
    if part not in ("multisine", "arrow", "all"):
        raise ValueError(f"part must be 'multisine', 'arrow' or 'all', got {part!r}")
    if part != "all" and file != "SNLS80mV.csv":
        raise ValueError(f"part={part!r} is defined for SNLS80mV.csv only; use part='all' for {file!r}")
    if path is not None:
        dirs = [Path(path)]
    elif os.environ.get(ENV_VAR):
        dirs = [Path(os.environ[ENV_VAR])]
    else:
        dirs = [
            Path.cwd() / ".." / "shared" / "data" / "silverbox",
            _REPO_ROOT / ".." / "shared" / "data" / "silverbox",
        ]
    tried = []
    for d in dirs:
        candidate = (d / file).resolve()
        tried.append(str(candidate))
        if candidate.is_file():
            data = _read_silverbox_csv(str(candidate), candidate.stat().st_mtime_ns)
            break
    else:
        raise FileNotFoundError(
            f"Silverbox file {file!r} not found; tried: {', '.join(tried)}. Get the data from "
            "the nonlinear system identification benchmark collection "
            "(https://www.nonlinearbenchmark.org, or the `nonlinear-benchmarks` Python package, "
            "which downloads it) and pass its directory as `path` "
            f"or set ${ENV_VAR}."
        )
    if part == "arrow":
        data = data[:SILVERBOX_ARROW_END]
    elif part == "multisine":
        data = data[SILVERBOX_ARROW_END:]
    return data[:, :1].copy(), data[:, 1:2].copy()
