"""Shared fixtures of the engine tests: linear mean functions and a small linear-Gaussian system."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from reference import simulate_linear
from torch import nn

from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.core.noise import GaussianNoise, StudentTNoise

DTYPE = torch.float64


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    """Run the suite single-threaded.

    The engine runs many small per-step kernels.  On a 2-core machine that is busy with anything
    else, torch's intra-op thread pool makes them 100-300x slower (measured: a 30-step filter took
    0.01 s CPU with 1 thread and 1.3 s with 2 threads while the other core was loaded; docs/method.md §7).
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def kernel_imports_this_checkout(monkeypatch):
    """A notebook kernel or subprocess (which inherits the environment) imports this checkout's
    ``torch_nssm`` and ``examples/``, not an installed copy."""
    repo = Path(__file__).resolve().parents[1]
    paths = [str(repo), str(repo / "examples"), os.environ.get("PYTHONPATH", "")]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in paths if p))


class LinearF(nn.Module):
    """``f(x, u) = x A^T + u B^T`` with matrix parameters (a plain module: no closed form)."""

    def __init__(self, A, B):
        super().__init__()
        self.A = nn.Parameter(torch.as_tensor(np.asarray(A), dtype=DTYPE).clone())
        self.B = nn.Parameter(torch.as_tensor(np.asarray(B), dtype=DTYPE).clone())

    def forward(self, x, u):
        return x @ self.A.T + u @ self.B.T


class LinearG(nn.Module):
    """``g(x, u) = x C^T + u D^T`` with matrix parameters."""

    def __init__(self, C, D):
        super().__init__()
        self.C = nn.Parameter(torch.as_tensor(np.asarray(C), dtype=DTYPE).clone())
        self.D = nn.Parameter(torch.as_tensor(np.asarray(D), dtype=DTYPE).clone())

    def forward(self, x, u):
        return x @ self.C.T + u @ self.D.T


class NonlinearF(nn.Module):
    """``f(x, u) = [a x_1 + b u, 0.5 x_2 + c sin(x_1)]`` (2 states, parameters a, b, c)."""

    def __init__(self, a=0.9, b=1.0, c=0.4):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(float(a), dtype=DTYPE))
        self.b = nn.Parameter(torch.tensor(float(b), dtype=DTYPE))
        self.c = nn.Parameter(torch.tensor(float(c), dtype=DTYPE))

    def forward(self, x, u):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack(
            [self.a * x1 + self.b * u[..., 0], 0.5 * x2 + self.c * torch.sin(x1)], -1
        )


class CosineG(nn.Module):
    """``g(x, u) = [c cos(x_1), x_1 + 0.5 x_2 + d u]`` (2 outputs, parameters c, d)."""

    def __init__(self, c=1.0, d=0.3):
        super().__init__()
        self.c = nn.Parameter(torch.tensor(float(c), dtype=DTYPE))
        self.d = nn.Parameter(torch.tensor(float(d), dtype=DTYPE))

    def forward(self, x, u):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([self.c * torch.cos(x1), x1 + 0.5 * x2 + self.d * u[..., 0]], -1)


class Paper41F(nn.Module):
    """The paper's §4.1 transition ``f = a x + b u`` (true a = 0.9, b = 1)."""

    def __init__(self, a=0.9, b=1.0):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(float(a), dtype=DTYPE))
        self.b = nn.Parameter(torch.tensor(float(b), dtype=DTYPE))

    def forward(self, x, u):
        return self.a * x + self.b * u


class Paper41G(nn.Module):
    """The paper's §4.1 observation ``g = c cos(x)`` (true c = 1)."""

    def __init__(self, c=1.0):
        super().__init__()
        self.c = nn.Parameter(torch.tensor(float(c), dtype=DTYPE))

    def forward(self, x, u):
        return self.c * torch.cos(x)


def _t(a) -> torch.Tensor:
    return torch.as_tensor(a, dtype=DTYPE)


def noise_model(Rv, dof=math.inf):
    """Student-t noise of scale ``Rv`` and ``dof`` degrees of freedom (Gaussian for ``inf``)."""
    Rv = torch.as_tensor(Rv, dtype=DTYPE)
    if math.isinf(float(dof)):
        return GaussianNoise(Rv)
    return StudentTNoise(Rv, torch.as_tensor(float(dof), dtype=DTYPE))


def make_model(f, g, Rw, Rv, dof, x0_mean, x0_cov) -> StateSpaceModel:
    """A :class:`StateSpaceModel` from tensors or arrays (Gaussian noise for infinite ``dof``)."""
    return StateSpaceModel(f, g, _t(Rw), noise_model(Rv, dof), _t(x0_mean), _t(x0_cov))


def nonlinear_model(dof: float = 3.0) -> StateSpaceModel:
    """2 states, 2 outputs, 1 input; full ``Rw`` and ``Rv``."""
    return StateSpaceModel(
        f=NonlinearF(),
        g=CosineG(),
        Rw=_t([[0.1, 0.04], [0.04, 0.2]]),
        noise=noise_model([[0.1, 0.03], [0.03, 0.2]], dof),
        x0_mean=_t([0.0, 0.5]),
        x0_cov=_t([[1.0, 0.2], [0.2, 0.5]]),
    )


def paper_model(dof: float = 3.0) -> StateSpaceModel:
    """The paper's §4.1 system: ``x+ = 0.9 x + u + w``, ``y = cos x + v``, variances 0.1."""
    return make_model(Paper41F(), Paper41G(), [[0.1]], [[0.1]], dof, [0.0], [[1.0]])


def simulate(model: StateSpaceModel, lengths, rng: np.random.Generator, outlier_rate: float = 0.0):
    """Lists of inputs ``(T_b, 1)`` and outputs ``(T_b, p)`` of ``model`` (Gaussian noise of
    covariances ``Rw``, ``Rv``), with a fraction of the outputs replaced by 5.0 (outliers)."""
    nx = model.state_dim
    Cw = torch.linalg.cholesky(model.Rw)
    Cv = torch.linalg.cholesky(model.Rv)
    us, ys = [], []
    with torch.no_grad():
        for n in lengths:
            x = model.x0_mean + torch.linalg.cholesky(model.x0_cov) @ _t(rng.normal(size=nx))
            u = _t(rng.normal(size=(n, 1)))
            y = []
            for k in range(n):
                y.append(model.g(x, u[k]) + Cv @ _t(rng.normal(size=Cv.shape[0])))
                x = model.f(x, u[k]) + Cw @ _t(rng.normal(size=nx))
            y = torch.stack(y)
            y[_t(rng.random(n)) < outlier_rate] = 5.0
            us.append(u)
            ys.append(y)
    return us, ys


def simulate_t_outputs(R, dof: float, T: int, B: int, rng: np.random.Generator):
    """Known "states" ``x`` (T, B, p) and ``y = x + v`` with ``v ~ St(0, R, dof)`` (numpy)."""
    R = np.asarray(R, dtype=np.float64)
    p = R.shape[0]
    x = rng.normal(size=(T, B, p))
    v = rng.multivariate_normal(np.zeros(p), R, size=(T, B))
    if not math.isinf(dof):
        lam = rng.gamma(0.5 * dof, 2.0 / dof, size=(T, B, 1))
        v = v / np.sqrt(lam)
    return x, x + v


@dataclass
class LinearSystem:
    """The 2-state, 2-output, 1-input linear-Gaussian test system (full ``Q`` and ``R``)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    m0: np.ndarray
    P0: np.ndarray

    def model(self, dof: float = math.inf) -> StateSpaceModel:
        t = lambda a: torch.as_tensor(a, dtype=DTYPE)  # noqa: E731
        return StateSpaceModel(
            f=LinearF(self.A, self.B),
            g=LinearG(self.C, self.D),
            Rw=t(self.Q),
            noise=noise_model(self.R, dof),
            x0_mean=t(self.m0),
            x0_cov=t(self.P0),
        )

    def matrices(self):
        return self.A, self.B, self.C, self.D, self.Q, self.R, self.m0, self.P0


def make_linear_system() -> LinearSystem:
    return LinearSystem(
        A=np.array([[0.8, 0.2], [-0.1, 0.7]]),
        B=np.array([[1.0], [0.5]]),
        C=np.array([[1.0, 0.0], [0.5, 1.0]]),
        D=np.array([[0.1], [0.0]]),
        Q=np.array([[0.10, 0.03], [0.03, 0.05]]),
        R=np.array([[0.20, 0.05], [0.05, 0.10]]),
        m0=np.array([0.5, -0.3]),
        P0=np.array([[0.5, 0.1], [0.1, 0.3]]),
    )


@pytest.fixture(scope="session")
def linear_system() -> LinearSystem:
    return make_linear_system()


#: Length of the linear-Gaussian test record.
N_STEPS = 100


@pytest.fixture(scope="session")
def record():
    """The linear-Gaussian system and one record of it: ``(system, u (N_STEPS, 1), y (N_STEPS, 2))``."""
    sysm = make_linear_system()
    rng = np.random.default_rng(0)
    u = rng.normal(size=(N_STEPS, 1))
    _, y = simulate_linear(*sysm.matrices(), u, rng)
    return sysm, u, y


def replicate(u: np.ndarray, y: np.ndarray, n_copies: int) -> SequenceBatch:
    """A batch of ``n_copies`` identical sequences (independent particle runs of one record)."""
    ut = torch.as_tensor(u, dtype=DTYPE)
    yt = torch.as_tensor(y, dtype=DTYPE)
    return SequenceBatch.from_sequences([ut] * n_copies, [yt] * n_copies)


def generator(seed: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(seed)
    return g


def inference_tensors(obj, path="est") -> list[str]:
    """Paths of the inference tensors reachable from ``obj`` (dataclass fields, containers,
    attributes): the per-step loops run in inference mode, and none of what they make may leave
    them as such (it could not be saved for backward nor changed in place outside)."""
    return [p for p, t in _tensors(obj, path, set()) if t.is_inference()]


def _tensors(obj, path, seen):
    """(path, tensor) of every tensor reachable from ``obj``: dataclass fields, containers, attributes."""
    if isinstance(obj, torch.Tensor):
        yield path, obj
        return
    if id(obj) in seen or obj is None or isinstance(obj, (int, float, bool, str, torch.nn.Module)):
        return
    seen.add(id(obj))
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    elif dataclasses.is_dataclass(obj):
        items = ((f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj))
    elif hasattr(obj, "__dict__"):
        items = vars(obj).items()
    else:
        return
    for k, v in items:
        yield from _tensors(v, f"{path}.{k}", seen)


def not_modifiable(obj, path="est") -> list[str]:
    """Paths of the floating tensors reachable from ``obj`` that cannot be changed in place in
    normal mode, with an operand that requires grad, because of inference mode: besides inference
    tensors, the views of ordinary tensors made in inference mode (which ``is_inference()`` does
    not show).  (Views made under ``no_grad`` refuse that too, as they always did: not counted.)
    Adds a zero, so the values stay; the tensors are part of a graph after."""
    bad = []
    for p, t in _tensors(obj, path, set()):
        if not t.is_floating_point():
            continue
        zero = torch.zeros((), dtype=t.dtype, device=t.device, requires_grad=True)
        try:
            with torch.enable_grad():
                t.add_(zero)
        except RuntimeError as error:
            if "inference" in str(error).lower():
                bad.append(p)
    return bad
