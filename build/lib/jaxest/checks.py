"""Argument checks that run before anything is traced.

Shapes are always checked; values (symmetry, definiteness, NaN) are checked when the arrays are
concrete, i.e. not JAX tracers (inside a user's ``jit`` the values are unknown until run time, and
trouble then shows in the result's ``status`` instead).
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(x) -> bool:
    """True for arrays whose values are known now (not tracers inside jit/vmap/grad)."""
    return not isinstance(x, jax.core.Tracer)


def check_matrix(name: str, value, shape=None, *, square=False, spd=False, psd=False, ndim=2):
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a well-formed matrix.

    ``ndim`` is the matrix's own rank; one extra leading axis (time) is allowed.
    ``shape`` (trailing dims, ``None`` entries are free) is checked against the last ``ndim`` axes.
    ``spd``/``psd`` require a symmetric positive (semi)definite matrix (checked when concrete).
    """
    if value is None:
        raise ValueError(f"{name}: expected an array, got None")
    arr = value
    if not hasattr(arr, "shape"):
        arr = np.asarray(arr)
    if arr.ndim not in (ndim, ndim + 1):
        raise ValueError(
            f"{name}: expected {ndim} dims (or {ndim + 1} with a time axis), got shape {arr.shape}"
        )
    trailing = arr.shape[arr.ndim - ndim :]
    if shape is not None:
        for want, got in zip(shape, trailing, strict=True):
            if want is not None and want != got:
                raise ValueError(f"{name}: expected trailing shape {tuple(shape)}, got {arr.shape}")
    if (square or spd or psd) and trailing[-1] != trailing[-2]:
        raise ValueError(f"{name}: must be square, got shape {arr.shape}")
    if not is_concrete(arr):
        return
    a = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if spd or psd:
        scale = max(np.max(np.abs(a)), np.finfo(np.float64).tiny)
        if np.max(np.abs(a - np.swapaxes(a, -1, -2))) > 1e-6 * scale:
            raise ValueError(f"{name}: must be symmetric")
        eig = np.linalg.eigvalsh(0.5 * (a + np.swapaxes(a, -1, -2)))
        if spd and np.min(eig) <= 0:
            raise ValueError(
                f"{name}: must be positive definite (smallest eigenvalue {np.min(eig):.3g})"
            )
        if psd and np.min(eig) < -1e-12 * scale:
            raise ValueError(
                f"{name}: must be positive semidefinite (smallest eigenvalue {np.min(eig):.3g})"
            )


def check_sequence(name: str, value, length=None, dim=None):
    """``value`` must be (T, dim); ``length`` is the T it must match (``None``: any)."""
    if value is None:
        raise ValueError(f"{name}: expected an array with a leading time axis, got None")
    shape = np.shape(value)
    if len(shape) != 2:
        raise ValueError(f"{name}: expected shape (T, {dim if dim else 'd'}), got {shape}")
    if length is not None and shape[0] != length:
        raise ValueError(f"{name}: has {shape[0]} time steps but the measurements have {length}")
    if dim is not None and shape[1] != dim:
        raise ValueError(f"{name}: expected {dim} columns, got {shape[1]}")


def check_prior(prior):
    """Raise ``ValueError`` naming ``init`` unless ``prior`` is a :class:`jaxest.Gaussian`."""
    from jaxest.run import Gaussian

    if not isinstance(prior, Gaussian):
        raise ValueError(f"init: expected jaxest.Gaussian(mean, cov), got {type(prior).__name__}")
    return prior


def _time_length(name, arr, T):
    if arr is not None and np.ndim(arr) == 3 and arr.shape[0] < T:
        raise ValueError(
            f"{name}: time-varying with {arr.shape[0]} steps, fewer than the {T} measurements"
        )


def check_filter_arguments(model, ys, inputs, init):
    """All checks of :func:`jaxest.filter`'s arguments."""
    from jaxest.models import LinearGaussian, NonlinearGaussian

    check_sequence("ys", ys)
    T, m = np.shape(ys)
    if inputs is not None:
        check_sequence("inputs", inputs, length=T)
    check_prior(init)
    if np.ndim(init.mean) != 1:
        raise ValueError(f"init.mean: expected a vector, got shape {np.shape(init.mean)}")
    n = np.shape(init.mean)[0]
    check_matrix("init.cov", init.cov, (n, n), spd=True, ndim=2)
    if np.ndim(init.cov) != 2:
        raise ValueError(f"init.cov: expected shape ({n}, {n}), got {np.shape(init.cov)}")
    check_matrix("model.R", model.R, (m, m), spd=True)
    if isinstance(model, LinearGaussian):
        check_matrix("model.F", model.F, (n, n))
        check_matrix("model.H", model.H, (m, n))
        q = n if model.G is None else np.shape(model.G)[-1]
        if model.G is not None:
            check_matrix("model.G", model.G, (n, q))
        check_matrix("model.Q", model.Q, (q, q), psd=True)
        for name in ("F", "H", "Q", "R", "G", "B", "D"):
            _time_length(f"model.{name}", getattr(model, name), T)
    elif isinstance(model, NonlinearGaussian):
        check_matrix("model.Q", model.Q, square=True, psd=True)
        for name in ("Q", "R"):
            _time_length(f"model.{name}", getattr(model, name), T)
    check_model_dimensions(model, init.mean, None if inputs is None else inputs[0], m)


def check_model_dimensions(model, x, u, m):
    """Evaluate the model abstractly at ``x`` and check the shapes it returns."""
    n = x.shape[0]
    try:
        mean, F, G, Q = jax.eval_shape(model.transition, x, u, 0)
        y_mean, H, _ = jax.eval_shape(model.observation, x, u, 0)
    except Exception as err:  # noqa: BLE001 - reported with the argument's name
        raise ValueError(
            f"model: cannot be evaluated at init.mean ({type(err).__name__}: {err})"
        ) from err
    expected = {
        "model transition mean": (mean.shape, (n,)),
        "model transition Jacobian F": (F.shape, (n, n)),
        "model noise gain G": (G.shape, (n, Q.shape[-1])),
        "model.Q": (Q.shape, (G.shape[-1], G.shape[-1])),
        "model observation mean h(x)": (y_mean.shape, (m,)),
        "model observation Jacobian H": (H.shape, (m, n)),
    }
    for name, (got, want) in expected.items():
        if tuple(got) != want:
            raise ValueError(f"{name}: expected shape {want}, got {tuple(got)}")
