"""Input checks that turn bad arguments into clear errors before any work starts."""

from __future__ import annotations

import numbers
import warnings

import numpy as np
import torch
from torch import Tensor, nn

__all__ = [
    "is_sequence_list",
    "as_sequence_list",
    "check_covariance",
    "check_vector",
    "check_positive",
    "check_choice",
    "check_device",
    "check_dtype",
    "check_module_shapes",
]


def _to_tensor(value, name: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(value, Tensor):
        t = value.detach()
        if t.is_complex():
            raise ValueError(f"{name}: Complex data not supported")
        if t.layout != torch.strided:
            raise TypeError(f"{name}: sparse input is not supported, pass a dense tensor")
    else:
        if hasattr(value, "tocsr") or hasattr(value, "todense"):  # scipy.sparse
            raise TypeError(f"{name}: sparse input is not supported, pass a dense array")
        try:
            arr = np.asarray(value)
            if np.iscomplexobj(arr):
                raise ValueError(f"{name}: Complex data not supported")
            arr = np.array(arr, dtype=np.float64)  # a copy: read-only inputs stay untouched
        except (TypeError, ValueError) as exc:
            if "Complex data" in str(exc):
                raise
            hint = ""
            if isinstance(value, (list, tuple)):
                hint = "; several records of different lengths go in a list of numpy arrays"
            raise TypeError(
                f"{name} must be array-like of real numbers, got {type(value).__name__} ({exc}){hint}"
            ) from exc
        t = torch.from_numpy(arr)
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64, torch.bool)):
        raise TypeError(f"{name} must hold real numbers, got dtype {t.dtype}")
    return t.to(device=device, dtype=dtype)


def _as_2d(t: Tensor, name: str) -> Tensor:
    if t.dim() == 1:
        return t.unsqueeze(-1)
    if t.dim() == 2:
        return t
    raise ValueError(
        f"{name} must be 1-D (n_samples,) or 2-D (n_samples, n_columns), got shape {tuple(t.shape)}"
    )


def _transposed_hint(name: str, t: Tensor) -> str:
    """For a 2-D record with fewer rows than columns: it looks transposed (rows are samples)."""
    if t.dim() != 2 or t.shape[0] >= t.shape[1]:
        return ""
    rows, cols = t.shape
    return (
        f"; {name} has shape ({rows}, {cols}): rows are samples and columns are channels, so this is "
        f"{rows} sample(s) of {cols} channels. Is it transposed? Pass {name}.T (shape ({cols}, {rows}))"
        + (f" or a 1-D array of {cols} samples" if rows == 1 else "")
    )


def _is_array(value) -> bool:
    """An array object (ndarray, tensor, pandas object...), not a number or a nested list."""
    if isinstance(value, (np.ndarray, Tensor)):
        return True
    return hasattr(value, "__array__") and not isinstance(value, numbers.Number)


def is_sequence_list(value) -> bool:
    """True for several records: a non-empty list or tuple of arrays (or tensors).

    A list of numbers or of Python lists is *one* record (its rows), as in scikit-learn; several
    records of possibly different lengths are passed as a list of numpy arrays or tensors.
    """
    return isinstance(value, (list, tuple)) and len(value) > 0 and all(_is_array(v) for v in value)


def as_sequence_list(
    u,
    y,
    *,
    dtype: torch.dtype,
    device: torch.device,
    n_inputs: int | None = None,
    n_outputs: int | None = None,
    require_y: bool = True,
) -> tuple[list[Tensor], list[Tensor] | None, bool]:
    """Validate ``u`` and ``y`` (one record, or lists of records) and convert them to 2-D tensors.

    ``u=None`` means a system without input (``nu = 0``).  NaN in ``y`` marks a missing output;
    NaN or infinity in ``u`` is an error.

    Parameters
    ----------
    u, y : array-like, list of array-like, or None
        One record (``(N,)`` or ``(N, n)``) or a list of records (see :func:`is_sequence_list`).
    dtype, device
        Of the tensors returned.
    n_inputs, n_outputs : int, optional
        Expected numbers of columns (those of the data a model was fitted on).
    require_y : bool, default=True
        Raise if ``y`` is None.

    Returns
    -------
    (list of Tensor, list of Tensor or None, bool)
        Inputs ``(T_b, nu)`` and outputs ``(T_b, p)`` of each record, and whether several records
        were given (a list) rather than one.
    """
    if y is None and require_y:
        raise ValueError("y is required: this estimator requires y to be passed, but the target y is None")
    multi = is_sequence_list(y) if y is not None else is_sequence_list(u)
    if multi:
        ys = list(y) if y is not None else None
        n_seq = len(ys) if ys is not None else len(u)
        if u is None:
            us = [None] * n_seq
        elif is_sequence_list(u):
            us = list(u)
            if len(us) != n_seq:
                raise ValueError(f"u and y must hold the same number of records, got {len(us)} and {n_seq}")
        else:
            raise ValueError("y is a list of records, so u must be a list of as many arrays (or None)")
    else:
        if y is not None and is_sequence_list(u):
            raise ValueError("u is a list of records, so y must be a list of as many arrays")
        us, ys = [u], ([y] if y is not None else None)
    out_u, out_y = [], ([] if ys is not None else None)
    for b in range(len(us)):
        tag = f"[{b}]" if multi else ""
        yb = None
        if ys is not None:
            yb = _as_2d(_to_tensor(ys[b], f"y{tag}", dtype, device), f"y{tag}")
            if yb.shape[0] < 2:
                raise ValueError(
                    f"y{tag} must have at least 2 samples, got {yb.shape[0]} sample(s)"
                    f"{_transposed_hint(f'y{tag}', yb)}"
                )
            if torch.isinf(yb).any():
                raise ValueError(f"y{tag} contains infinite values (use NaN for missing outputs)")
            if torch.isnan(yb).all():
                raise ValueError(f"y{tag} is all missing (NaN): nothing to fit")
            if n_outputs is not None and yb.shape[1] != n_outputs:
                raise ValueError(
                    f"y{tag} has {yb.shape[1]} output columns, expected {n_outputs} "
                    "(the model's number of outputs)"
                )
        if us[b] is None:
            if n_inputs not in (None, 0):
                raise ValueError(f"u is required: the model was fitted with {n_inputs} input columns")
            if yb is None:
                raise ValueError(
                    "u is required when y is not given (for a model without input pass "
                    "u of shape (n_samples, 0))"
                )
            ub = torch.zeros(yb.shape[0], 0, dtype=dtype, device=device)
        else:
            raw = _to_tensor(us[b], f"u{tag}", dtype, device)
            ub = _as_2d(raw, f"u{tag}")
            if ub.shape[0] == 0:
                raise ValueError(f"u{tag} is empty: it must have at least 1 sample")
            if not torch.isfinite(ub).all():
                bad = int(torch.nonzero(~torch.isfinite(ub).all(-1))[0])
                raise ValueError(
                    f"u{tag} contains NaN or infinite values (first at sample {bad}); "
                    "inputs cannot be missing"
                )
            if n_inputs is not None and ub.shape[1] != n_inputs:
                hint = ""
                if raw.dim() == 1:
                    hint = f"; a 1-D u is one input column: Reshape your data to (n_samples, {n_inputs})"
                elif ub.shape[0] == n_inputs and ub.shape[1] > 1:
                    hint = _transposed_hint(f"u{tag}", ub)
                raise ValueError(
                    f"u{tag} has {ub.shape[1]} input columns, expected {n_inputs} "
                    f"(the model's number of inputs){hint}"
                )
        if yb is not None and ub.shape[0] != yb.shape[0]:
            hint = _transposed_hint(f"u{tag}", ub) if ub.shape[1] == yb.shape[0] else ""
            raise ValueError(
                f"u{tag} and y{tag} must have the same length, got {ub.shape[0]} and {yb.shape[0]}{hint}"
            )
        out_u.append(ub)
        if out_y is not None:
            out_y.append(yb)
    return out_u, out_y, multi


def check_vector(value, name: str, dim: int | None, *, dtype, device) -> Tensor:
    """A finite 1-D vector (a scalar is a vector of length 1)."""
    t = _to_tensor(value, name, dtype, device).reshape(-1)
    if dim is not None and t.numel() != dim:
        raise ValueError(f"{name} must have {dim} entries, got {t.numel()}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {t.tolist()}")
    return t


def check_covariance(value, name: str, dim: int, *, dtype, device) -> Tensor:
    """A symmetric positive-definite ``(dim, dim)`` matrix; a scalar or vector means a diagonal."""
    t = _to_tensor(value, name, dtype, device)
    if t.dim() == 0 or (t.dim() == 1 and t.numel() == 1):
        t = t.reshape(()) * torch.eye(dim, dtype=dtype, device=device)
    elif t.dim() == 1:
        if t.numel() != dim:
            raise ValueError(f"{name} as a vector is a diagonal and must have {dim} entries, got {t.numel()}")
        t = torch.diag(t)
    if t.shape != (dim, dim):
        raise ValueError(f"{name} must be a ({dim}, {dim}) matrix, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    if not torch.allclose(t, t.T, rtol=1e-8, atol=1e-12):
        raise ValueError(f"{name} must be symmetric")
    eig = torch.linalg.eigvalsh(t)
    if eig.min() <= 0:
        raise ValueError(f"{name} must be positive definite, its eigenvalues are {eig.tolist()}")
    return t


def check_positive(value, name: str, *, integer: bool = False, minimum: float = 0.0, inclusive: bool = False):
    """A real (or integer) number ``> minimum`` (``>=`` when ``inclusive``)."""
    kind = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kind):
        raise TypeError(f"{name} must be {'an integer' if integer else 'a number'}, got {value!r}")
    ok = value >= minimum if inclusive else value > minimum
    if not ok or (not integer and np.isnan(value)):
        op = ">=" if inclusive else ">"
        raise ValueError(f"{name} must be {op} {minimum}, got {value!r}")
    return value


def check_choice(value, name: str, choices) -> str:
    """One of a fixed set of strings."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")
    return value


def check_dtype(dtype) -> torch.dtype:
    """``torch.float32`` or ``torch.float64``."""
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return dtype


def check_device(device) -> torch.device:
    """A torch device that exists on this machine."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device {device!r} is not a valid torch device") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} is not available: torch.cuda.is_available() is False")
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {device!r} is not available on this machine")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r} is not available: {torch.cuda.device_count()} CUDA device(s)")
    return dev


def check_module_shapes(f: nn.Module, g: nn.Module, nx: int, nu: int, p: int, *, dtype, device) -> None:
    """Call ``f`` and ``g`` once on a small batch and check their output shapes."""
    for name, module in (("f", f), ("g", g)):
        if not isinstance(module, nn.Module):
            raise TypeError(
                f"{name} must be a torch.nn.Module called as {name}(x, u), got {type(module).__name__}"
            )
    for name, module in (("f", f), ("g", g)):
        declared = getattr(module, "nx", None)
        if isinstance(declared, int) and not isinstance(declared, bool) and declared != nx:
            raise ValueError(
                f"x0_mean has {nx} entries but {name} ({type(module).__name__}) declares nx={declared} "
                f"states: x0_mean must hold one value per state ({declared})"
            )
    x = torch.zeros(3, nx, dtype=dtype, device=device)
    u = torch.zeros(3, nu, dtype=dtype, device=device)
    checks = (
        ("f", f, nx, "the state dimension len(x0_mean)"),
        ("g", g, p, "the number of outputs (columns of y)"),
    )
    for name, module, want, what in checks:
        try:
            with torch.no_grad():
                out = module(x, u)
        except Exception as exc:  # a user module can fail in any way: say where
            raise ValueError(
                f"{name}(x, u) failed on x of shape {tuple(x.shape)} and u of shape "
                f"{tuple(u.shape)} "
                f"({type(exc).__name__}: {exc}); check that nx = len(x0_mean) = {nx} and nu = {nu} "
                "match the module"
            ) from exc
        if not isinstance(out, Tensor) or tuple(out.shape) != (3, want):
            shape = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"{name}(x, u) must return shape (..., {want}) ({what}) for x of shape "
                f"(..., {nx}) (nx = len(x0_mean)) and u of shape (..., {nu}); "
                f"got {shape} for x of shape (3, {nx}){_state_dimension_hint(name, out, nx, want)}"
            )


def _state_dimension_hint(name: str, out, nx: int, want: int) -> str:
    """What a wrong output shape of ``f`` or ``g`` says about ``x0_mean``: ``f`` returning another
    number of states, or ``g`` returning one column per state entry (a module written for a
    single state applied elementwise to a longer ``x``), both point at ``len(x0_mean)``."""
    if not isinstance(out, Tensor) or out.dim() != 2 or out.shape[0] != 3:
        return ""
    m = int(out.shape[1])
    if name == "f" and m != nx:
        return (
            f". f returns {m} state(s) for {nx}: if the model has {m} state(s), x0_mean has the wrong "
            f"length ({nx} entries, needs {m})"
        )
    if name == "g" and m == nx and m != want:
        return (
            f". g returns one column per state entry: is x0_mean the right length ({nx} entries)? "
            "f ran elementwise on it, so its length sets nx"
        )
    return ""


# --------------------------------------------------------------------------------------------
# NumPy-side checks for the application modules (data generators, ready-made blocks).
# They coerce what NumPy accepts and raise ValueError naming the argument (a wrong type of
# number is a ValueError here, as the data generators have always reported it).
# --------------------------------------------------------------------------------------------

__all__ += [
    "check_count",
    "check_real",
    "check_pair",
    "check_vector_array",
    "check_matrix_array",
    "check_covariance_array",
    "as_rows_array",
]


def check_count(value, name: str, minimum: int = 1) -> int:
    """An integer ``>= minimum`` (bool excluded); ValueError otherwise."""
    try:
        check_positive(value, name, integer=True, minimum=minimum, inclusive=True)
    except TypeError:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}") from None
    return int(value)


def check_real(
    value,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """A real number (anything ``float()`` accepts, NaN excluded) within optional bounds."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if np.isnan(v):
        raise ValueError(f"{name} must not be NaN")
    below = low is not None and (v < low or (low_open and v == low))
    above = high is not None and (v > high or (high_open and v == high))
    if below or above:
        if high is None:
            raise ValueError(f"{name} must be {'>' if low_open else '>='} {low}, got {value!r}")
        if low is None:
            raise ValueError(f"{name} must be {'<' if high_open else '<='} {high}, got {value!r}")
        lb, rb = "(" if low_open else "[", ")" if high_open else "]"
        raise ValueError(f"{name} must lie in {lb}{low}, {high}{rb}, got {value!r}")
    return v


def check_pair(value, name: str) -> tuple[float, float]:
    """A finite pair ``(low, high)`` with ``low < high``."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high) of numbers, got {value!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi)) or not lo < hi:
        raise ValueError(f"{name} must be a finite pair with low < high, got {value!r}")
    return lo, hi


def _float_array(value, name: str) -> np.ndarray:
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None


def check_vector_array(value, name: str, dim: int, *, positive: bool = False) -> np.ndarray:
    """A finite float64 vector of shape ``(dim,)``; a scalar is repeated ``dim`` times."""
    arr = _float_array(value, name)
    if arr.ndim == 0:
        arr = np.full(dim, float(arr))
    if arr.shape != (dim,):
        raise ValueError(f"{name} must be a scalar or have shape ({dim},), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be positive, got {arr.tolist()}")
    return arr


def check_matrix_array(value, name: str, shape: tuple[int, int]) -> np.ndarray:
    """A finite float64 matrix of the given shape; a scalar means ``value * I`` (square) or a
    matrix filled with it."""
    arr = _float_array(value, name)
    if arr.ndim == 0:
        arr = float(arr) * np.eye(*shape) if shape[0] == shape[1] else np.full(shape, float(arr))
    if arr.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def check_covariance_array(value, name: str, dim: int) -> np.ndarray:
    """A symmetric positive semi-definite ``(dim, dim)`` float64 matrix (singular allowed, e.g. a
    noise-free simulation); a scalar means ``value * I`` and a vector a diagonal."""
    arr = _float_array(value, name)
    if arr.ndim == 0:
        arr = arr * np.eye(dim)
    elif arr.ndim == 1 and arr.shape == (dim,):
        arr = np.diag(arr)
    elif arr.shape != (dim, dim):
        raise ValueError(
            f"{name} must be a scalar, a length-{dim} vector or a ({dim}, {dim}) matrix, "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-14):
        raise ValueError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(arr).min() < -1e-12 * max(1.0, float(np.abs(arr).max())):
        raise ValueError(f"{name} must be positive semi-definite")
    return arr


def as_rows_array(value, name: str, n: int) -> np.ndarray:
    """Data as float64 rows of width ``n``, shape ``(rows, n)``; a 1-D array is one column when
    ``n == 1``.  NaN is kept (callers ignore it)."""
    arr = _float_array(value, name)
    if arr.ndim == 1 and n == 1:
        arr = arr[:, None]
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got shape {arr.shape}")
    return arr.reshape(-1, n)


def check_data_against_model(data, f: nn.Module, g: nn.Module, nu: int, p: int) -> None:
    """Contradictions between the data (a ``SequenceBatch``) and the model that would fit nonsense
    without a word: an error, or a warning for a record too short for the free parameters."""
    for label, module in (("f", f), ("g", g)):
        declared = getattr(module, "nu", None)
        if isinstance(declared, int) and declared != nu:
            raise ValueError(
                f"u has {nu} input column(s) but {label} ({type(module).__name__}) declares nu={declared}: "
                "pass the inputs the module was built for"
            )
    y = data.y
    for j in range(p):
        col = y[..., j][~torch.isnan(y[..., j])]
        if col.numel() > 1 and bool((col == col[0]).all()):
            raise ValueError(
                f"y{'' if p == 1 else f'[:, {j}]'} is constant ({float(col[0]):g} at every observed sample): "
                "there is nothing to identify"
            )
    n_obs = int(data.obs_mask.any(-1).sum())
    n_free = sum(int(q.numel()) for m in (f, g) for q in m.parameters() if q.requires_grad)
    if n_obs < 10 * max(n_free, 1):
        warnings.warn(
            f"only {n_obs} observed samples for {n_free} free parameters of f and g (plus the noise "
            "parameters): the estimates will be poorly determined; use a longer record",
            UserWarning,
            stacklevel=5,
        )


def is_1d_record(y, multi: bool) -> bool:
    """Whether the (first) record of ``y`` is 1-D (its predictions then come back 1-D)."""
    first = y[0] if multi else y
    return (first.dim() if isinstance(first, torch.Tensor) else np.asarray(first).ndim) == 1
